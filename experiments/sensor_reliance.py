"""Which sensors does an expert's cost hang on, and do those sensors read as Safety-Gymnasium's?

    python -m experiments.sensor_reliance [--task CarCircle2] [--limit 20] [--episodes 128]
        [--replays 6] [--out experiments/results/sensor_reliance.json]

1. Reliance (ours only): the source task's expert of cost limit `limit` (last snapshot,
   `sim2sim.pick_expert`) in `task`, `episodes` episodes, mean and sampled actions; then again
   with one sensor group at a time frozen at its mean over the unfrozen run. A group whose
   freezing moves the episode cost a lot steers the expert near the cost boundary.
2. Readings (both simulators, needs the peer venv): the expert's own action sequences of
   `replays` episodes (mean actions, our simulator) replayed open-loop in both, 4 layouts each;
   per sensor group the mean and std of each side's readings over steps 100-500, and the
   forward speed and yaw rate (the dynamics the sequence drives). The Car's caster-ball sensors
   integrate the ball's rolling, so a few percent of difference in its rate becomes a different
   orientation within tens of steps; the marginals say whether the two balls roll alike.
Writes JSON and markdown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown

# Observation slices of the Car's 24 robot sensors (the task's lidars follow them).
GROUPS = {"accelerometer": (0, 3), "velocimeter": (3, 6), "gyro": (6, 9),
          "magnetometer": (9, 12), "ball angular velocity": (12, 15),
          "ball orientation": (15, 24)}
STEPS = 500


def expert_rollouts(task: str, limit: float, episodes: int, deterministic: bool,
                    frozen: tuple[int, int] | None, fill) -> dict[str, np.ndarray]:
    """Episode costs [episodes], mean observation per episode [episodes, obs] and the actions
    [episodes, STEPS, 2] of the expert in `task`, with obs[frozen] replaced by `fill`."""
    import jax
    import jax.numpy as jnp

    from experiments.sim2sim import expert_act, pick_expert
    from safecdt_jax import envs
    from safecdt_jax.experts.collect import snapshot_path

    source = task[:-1] + "1"
    act = expert_act(snapshot_path(source), pick_expert(source, limit), deterministic)
    env, params = envs.make(task)
    lo, hi = frozen or (0, 0)
    mask = (jnp.arange(env.observation_size) >= lo) & (jnp.arange(env.observation_size) < hi)

    def episode(key):
        def step(state, k):
            a = act(k, jnp.where(mask, fill, state.obs))
            nxt = env.step(state, a, params)
            return nxt, (nxt.cost, nxt.obs, a)

        k0, k1 = jax.random.split(key)
        _, (c, o, a) = jax.lax.scan(step, env.reset(k0, params), jax.random.split(k1, STEPS))
        return c.sum(), o.mean(0), a

    keys = jax.random.split(jax.random.PRNGKey(0), episodes)
    cost, obs, actions = jax.jit(jax.vmap(episode))(keys)
    return {"cost": np.asarray(cost), "obs": np.asarray(obs), "actions": np.asarray(actions)}


def reliance(task: str, limit: float, episodes: int) -> list[dict]:
    """Per policy (mean, sampled) and frozen group: mean and median episode cost."""
    rows = []
    for det in (True, False):
        base = expert_rollouts(task, limit, episodes, det, None, 0.0)
        fill = base["obs"].mean(0)
        policy = "mean" if det else "sampled"
        rows.append({"policy": policy, "frozen": "-", "cost": float(base["cost"].mean()),
                     "median": float(np.median(base["cost"]))})
        for name, span in GROUPS.items():
            c = expert_rollouts(task, limit, episodes, det, span, fill)["cost"]
            rows.append({"policy": policy, "frozen": name, "cost": float(c.mean()),
                         "median": float(np.median(c))})
    return rows


def readings(task: str, limit: float, replays: int) -> list[dict]:
    """Per sensor group: mean and std of the readings over steps 100-500 on each side, the
    expert's mean-action sequences replayed open-loop; and the speed (m/s) and yaw rate."""
    from experiments.sim2sim import native, ours_trace

    actions = expert_rollouts(task, limit, replays, True, None, 0.0)["actions"]
    ours, theirs = [], []
    for seq in actions:
        script = seq.tolist()
        ours.append(ours_trace(task, 4, STEPS, 0, script)[:, 100:])
        theirs.append(native({"cmd": "trace", "task": task, "episodes": 4, "steps": STEPS,
                              "seed": 0, "actions": script})["obs"][:, 100:])
    o, t = np.concatenate(ours), np.concatenate(theirs)
    rows = [{"group": "forward speed (m/s)", "ours_mean": float(-o[..., 4].mean()),
             "theirs_mean": float(-t[..., 4].mean()), "ours_std": float(o[..., 4].std()),
             "theirs_std": float(t[..., 4].std())},
            {"group": "yaw rate (rad/s)", "ours_mean": float(o[..., 8].mean()),
             "theirs_mean": float(t[..., 8].mean()), "ours_std": float(o[..., 8].std()),
             "theirs_std": float(t[..., 8].std())}]
    for name, (lo, hi) in GROUPS.items():
        # Mean over the group's dimensions of each dimension's mean and std.
        rows.append({"group": name, "ours_mean": float(o[..., lo:hi].mean((0, 1)).mean()),
                     "theirs_mean": float(t[..., lo:hi].mean((0, 1)).mean()),
                     "ours_std": float(o[..., lo:hi].std((0, 1)).mean()),
                     "theirs_std": float(t[..., lo:hi].std((0, 1)).mean())})
    return rows


def main(argv: list[str] | None = None) -> None:
    """Command line: measure, print the tables, write JSON and markdown."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarCircle2")
    ap.add_argument("--limit", type=float, default=20.0)
    ap.add_argument("--episodes", type=int, default=128)
    ap.add_argument("--replays", type=int, default=6)
    ap.add_argument("--no-native", action="store_true", help="skip part 2 (no peer venv)")
    ap.add_argument("--out", type=Path,
                    default=Path("experiments/results/sensor_reliance.json"))
    args = ap.parse_args(argv)
    if not args.task.startswith("Car"):
        raise SystemExit(f"--task: the sensor groups are the Car's, got {args.task}")
    command = "python -m experiments.sensor_reliance " + " ".join(
        sys.argv[1:] if argv is None else argv)
    rel = reliance(args.task, args.limit, args.episodes)
    read = [] if args.no_native else readings(args.task, args.limit, args.replays)
    write_json(args.out, {"command": command, "machine": machine(), "task": args.task,
                          "limit": args.limit, "reliance": rel, "readings": read})
    body = f"Expert of cost limit {args.limit:g} in {args.task}, {args.episodes} episodes.\n\n"
    body += markdown_table(["policy", "sensor group frozen at its mean", "cost", "median"],
                           [[r["policy"], r["frozen"], f"{r['cost']:.1f}", f"{r['median']:.1f}"]
                            for r in rel])
    if read:
        body += (f"\n\nThe expert's mean-action sequences ({args.replays} episodes) replayed "
                 "open-loop in both simulators, steps 100-500 (group rows: the mean over the "
                 "group's dimensions of each dimension's mean and std).\n\n")
        body += markdown_table(["reading", "mean ours / SG", "std ours / SG"],
                               [[r["group"], f"{r['ours_mean']:.3f} / {r['theirs_mean']:.3f}",
                                 f"{r['ours_std']:.3f} / {r['theirs_std']:.3f}"] for r in read])
    write_markdown(args.out.with_suffix(".md"), "Which sensors an expert's cost hangs on",
                   command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
