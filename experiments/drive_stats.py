"""How an expert drives in each simulator: speed, turning, actions and goal-seeking (issue 48).

    python -m experiments.drive_stats [--task CarGoal1] [--limit 25] [--episodes 32]
        [--native-cone pyramidal|elliptic] [--out experiments/results/drive_stats.json]

The source task's expert (`sim2sim.pick_expert`), mean and sampled actions, closed loop in
both simulators on each side's own layouts (the native side records through the peer's
`policy` request). From every step's observation (before the action) and action:
- goals per episode and steps per goal; the goal's distance (m) read from the goal lidar
  (3 m range) the step after a goal was met (how far the next goal spawns) and at every step;
- the heading error to the goal (deg, from the goal lidar's strongest bin: 22.5 deg bins),
  measured from body +y, the way the CarGoal1 expert mostly drives;
- the speed toward body +y (m/s, velocimeter y: negative torques drive that way, positive
  ones toward -y), its magnitude, and |yaw rate| (rad/s, gyro z);
- the executed action's drive (a0 + a1) / 2 and turn |a0 - a1| / 2 (the Car's torques
  clip(a, +-0.02) / 0.02: a raw action of 0.5 drives as hard as 1), and the share of actions
  at the torque limit;
- the speed per drive bin, the part of the speed that the dynamics decide for a given
  action: if the bins agree and the marginals do not, the policy acts differently (what it
  sees differs); if the bins differ, the car answers the same action differently;
- (Circle tasks) how the laps meet the walls (`lap_summary`), from positions that the circle
  lidar and the magnetometer give (`circle_positions`).
Then (`recovery`) a turn and the recovery from it, open loop from rest in both simulators, in
each travel direction: 100 steps straight, 30 of a one-wheel turn or a spin, 100 straight
again (native: 8 layouts; ours: the floor is flat, 1). Per script the peak |yaw rate| at the
turn's onset (steps 100-110), the turn's steady yaw rate (120-130), the yaw rate left over
after it (135-195: a car that drives straight again reads 0) and the speed regained (130-160).
`--native-cone elliptic` runs the native side with MuJoCo's elliptic friction cone instead of
its default pyramidal one (what native's behaviour owes to the cone). Writes JSON and markdown.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown

DRIVE_BINS = (-1.01, 0.0, 0.5, 0.8, 0.95, 1.01)
VELOCIMETER, GYRO_Z, MAGNETOMETER = 3, 8, 9  # Car observation dims (x, y of each)


def ours_recorded(task: str, snapshot_file: Path, index: int, episodes: int,
                  deterministic: bool) -> dict[str, np.ndarray]:
    """Our side of `native.py`'s recorded `policy`: obs [E, T, D] before each action, actions
    [E, T, 2] and goal_met [E, T], one jitted vmap over `episodes` keys from seed 0."""
    import jax

    from experiments.sim2sim import expert_act
    from safecdt_jax import envs

    act = expert_act(snapshot_file, index, deterministic)
    env, params = envs.make(task)

    def episode(key):
        def step(state, k):
            a = act(k, state.obs)
            nxt = env.step(state, a, params)
            return nxt, (state.obs, a, nxt.info["goal_met"] > 0, nxt.cost > 0)

        k0, k1 = jax.random.split(key)
        _, out = jax.lax.scan(step, env.reset(k0, params),
                              jax.random.split(k1, env.episode_length))
        return out

    keys = jax.random.split(jax.random.PRNGKey(0), episodes)
    obs, actions, goal_met, cost = jax.jit(jax.vmap(episode))(keys)
    return {"obs": np.asarray(obs), "actions": np.asarray(actions),
            "goal_met": np.asarray(goal_met), "cost": np.asarray(cost).sum(1)}


def heading(obs: np.ndarray) -> np.ndarray:
    """World heading (rad, unwrapped along the last-but-one axis) from the magnetometer's body
    x, y readings of the world field (0, -0.5, 0): (-0.5 sin psi, -0.5 cos psi)."""
    mx, my = obs[..., MAGNETOMETER], obs[..., MAGNETOMETER + 1]
    return np.unwrap(np.arctan2(-mx, -my), axis=-1)


def circle_positions(obs: np.ndarray, n_sensors: int) -> tuple[np.ndarray, np.ndarray]:
    """World x, y (m) of the agent from a Circle task's observations [..., T, D]: the circle
    lidar's strongest bin and its aliased neighbour give the origin's body-frame distance and
    bearing (`envs.geometry.pseudo_lidar`, 6 m range), the magnetometer the heading. Exact
    while the origin is in range."""
    from safecdt_jax.envs.circle import LIDAR_RANGE

    lidar = obs[..., n_sensors:n_sensors + 16]
    top = lidar.argmax(-1)
    s = np.take_along_axis(lidar, top[..., None], -1)[..., 0]
    after = np.take_along_axis(lidar, ((top + 1) % 16)[..., None], -1)[..., 0]
    theta = (top + np.where(s > 0, after / np.maximum(s, 1e-9), 0.0)) * 2 * np.pi / 16
    dist, psi = LIDAR_RANGE * (1.0 - s), heading(obs)
    rx, ry = dist * np.cos(theta), dist * np.sin(theta)  # the origin, in the body frame
    return (-(np.cos(psi) * rx - np.sin(psi) * ry), -(np.sin(psi) * rx + np.cos(psi) * ry))


def lap_summary(obs: np.ndarray, n_sensors: int, boundary: float,
                dt: float) -> dict[str, float]:
    """How a Circle episode's laps meet the walls at |x| = `boundary` (m), from
    `circle_positions`: steps beyond per episode, wall entries per episode, episodes with one,
    the share of steps within 0.125 m inside the wall, the mean distance from the origin
    (steps 100 on), the speed toward the wall at an entry (m/s) and the median of each
    episode's largest |x|; `dt`: seconds per env step. Also the laps' curvature: the path
    speed (m/s) and net heading rate (rad/s, from the magnetometer) from step 100 on, and their
    ratio, the radius (m) the car curves at."""
    x, y = circle_positions(obs, n_sensors)
    ax = np.abs(x)
    out = ax > boundary
    entry = out[:, 1:] & ~out[:, :-1]
    toward = np.diff(ax, axis=1) / dt
    return {"steps_beyond": float(out.sum(1).mean()), "wall_entries": float(entry.sum(1).mean()),
            "episodes_with_entry": float((entry.sum(1) > 0).sum()),
            "near_wall_share": float(((ax > boundary - 0.125) & ~out).mean()),
            "radius": float(np.hypot(x, y)[:, min(100, x.shape[1] // 2):].mean()),
            "entry_speed": float(toward[entry].mean()) if entry.any() else float("nan"),
            "median_max_abs_x": float(np.median(ax.max(1))),
            **curvature(x, y, heading(obs), dt)}


def curvature(x: np.ndarray, y: np.ndarray, psi: np.ndarray, dt: float) -> dict[str, float]:
    """Path speed (m/s), net heading rate (rad/s) and their ratio, the curving radius (m), of
    episodes' positions and headings [E, T] from step min(100, T / 2) on."""
    start = min(100, x.shape[1] // 2)
    seconds = (x.shape[1] - 1 - start) * dt
    path = np.hypot(np.diff(x[:, start:], axis=1), np.diff(y[:, start:], axis=1)).sum(1)
    speed, rate = float(path.mean() / seconds), float((psi[:, -1] - psi[:, start]).mean()
                                                       / seconds)
    return {"path_speed": speed, "net_heading_rate": rate,
            "curving_radius": speed / rate if rate else float("nan")}


def drive_summary(rec: dict[str, np.ndarray], n_sensors: int, goal_task: bool = True,
                  limit: float = 1.0, boundary: float | None = None,
                  dt: float = 0.04) -> dict[str, float | list]:
    """The statistics of the module docstring from one side's recorded episodes (the goal
    statistics only for a Goal task: `goal_task`; the walls' `lap_summary` when a Circle
    task's `boundary` is given; `dt`: seconds per env step); actions are clipped at `limit`
    (the Car's torque limit 0.02) and read in its units."""
    from safecdt_jax.envs.goal import LIDAR_RANGE

    obs, a, met = rec["obs"], rec["actions"].astype(np.float64), rec["goal_met"].astype(bool)
    # Positive torques drive toward body -y, negative ones toward +y: the velocimeter's y
    # reads -speed when driving -y.
    speed, yaw = obs[..., 4], np.abs(obs[..., 8])
    a = np.clip(a, -limit, limit) / limit  # what the actuators execute, in units of the limit
    drive, turn = a.mean(-1), np.abs(a[..., 0] - a[..., 1]) / 2
    out = {}
    if goal_task:
        goal = obs[..., n_sensors:n_sensors + 16]
        dist = LIDAR_RANGE * (1.0 - goal.max(-1))
        bin_angle = (np.argmax(goal, -1) + 0.5) * 2 * np.pi / 16
        # Heading error from the direction the expert mostly drives, body +y (90 deg).
        heading = np.abs(np.angle(np.exp(1j * (bin_angle - np.pi / 2))))
        spawn = dist[:, 1:][met[:, :-1]]
        goals = met.sum(1)
        out = {"goals": float(goals.mean()),
               "steps_per_goal": float(met.size / max(goals.sum(), 1)),
               "spawn_distance": float(spawn.mean()) if spawn.size else float("nan"),
               "goal_distance": float(dist.mean()),
               "heading_error_deg": float(np.degrees(heading).mean())}
    out |= {"cost": float(np.mean(rec["cost"])), "median_cost": float(np.median(rec["cost"])),
            "speed_plus_y": float(speed.mean()), "abs_speed": float(np.abs(speed).mean()),
            "abs_yaw_rate": float(yaw.mean()), "drive": float(drive.mean()),
            "abs_turn": float(turn.mean()), "saturated": float((np.abs(a) >= 0.999).mean())}
    idx = np.digitize(drive, DRIVE_BINS) - 1
    if boundary is not None:
        out |= lap_summary(obs, n_sensors, boundary, dt)
    out["speed_by_drive"] = [float(speed[idx == i].mean()) if (idx == i).sum() >= 200 else None
                             for i in range(len(DRIVE_BINS) - 1)]
    out["share_by_drive"] = [float((idx == i).mean()) for i in range(len(DRIVE_BINS) - 1)]
    return out


def native_recorded(task: str, limit: float, episodes: int,
                    cone: str = "pyramidal") -> dict[str, dict]:
    """Native's recorded episodes of the task's expert (`sim2sim.pick_expert`) by action mode
    ("mean", "sampled"): the peer's `policy` request with `record` (cached), native's friction
    cone `cone`."""
    from experiments.sim2sim import export_policy, native, pick_expert
    from safecdt_jax.experts.collect import snapshot_path

    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "policy.npz"
        export_policy(snapshot_path(task), pick_expert(task, limit), weights)
        return {"mean" if det else "sampled": native(
            {"cmd": "policy", "task": task, "weights": str(weights), "episodes": episodes,
             "seed": 0, "deterministic": det, "record": True, **_cone(cone)})
            for det in (True, False)}


def compare(task: str, limit: float, episodes: int, cone: str = "pyramidal") -> list[dict]:
    """Per action mode, our and native's `drive_summary` of the task's expert in `task`
    (native's friction cone `cone`)."""
    from experiments.sim2sim import pick_expert
    from safecdt_jax import envs
    from safecdt_jax.experts.collect import snapshot_path

    index = pick_expert(task, limit)
    env, params = envs.make(task)
    robot = env.robot
    boundary = float(params.boundary) if "Circle" in task else None
    n_sensors, torque = robot.n_sensors, getattr(robot, "torque_limit", 1.0)
    goal_task = "Goal" in task
    theirs = native_recorded(task, limit, episodes, cone)
    rows = []
    for mode in ("mean", "sampled"):
        o = ours_recorded(task, snapshot_path(task), index, episodes, mode == "mean")
        rows.append({"policy": mode,
                     "ours": drive_summary(o, n_sensors, goal_task, torque, boundary, env.dt),
                     "theirs": drive_summary(theirs[mode], n_sensors, goal_task, torque,
                                             boundary, env.dt)})
    return rows


RECOVERY = {"one wheel": ((1.0, 1.0), (1.0, 0.0)), "spin": ((1.0, 1.0), (1.0, -1.0))}


def recovery_scripts() -> list[tuple[str, np.ndarray]]:
    """Each `RECOVERY` manoeuvre in both travel directions: positive torques drive toward body
    -y, the same script negated toward +y. Actions [230, 2]."""
    out = []
    for name, (straight, turn) in RECOVERY.items():
        acts = np.array([straight] * 100 + [turn] * 30 + [straight] * 100)
        out += [(f"{name}, toward -y", acts), (f"{name}, toward +y", -acts)]
    return out


def _cone(cone: str) -> dict:
    """The native request's cone field: absent for the default, so cached runs stay valid."""
    return {} if cone == "pyramidal" else {"cone": cone}


def recovery(task: str, cone: str = "pyramidal") -> list[dict]:
    """Per `recovery_scripts` script, each side's onset peak, turn and leftover |yaw rate|
    (rad/s, signed by the turn's direction) and regained speed (m/s), as the docstring says."""
    from experiments.sim2sim import native, ours_trace

    rows = []
    for name, acts in recovery_scripts():
        script = acts.tolist()
        o = ours_trace(task, 1, len(acts), 0, script).mean(0)
        t = native({"cmd": "trace", "task": task, "episodes": 8, "steps": len(acts), "seed": 0,
                    "actions": script, **_cone(cone)})["obs"].mean(0)
        row = {"script": name}
        for side, x in (("ours", o), ("theirs", t)):
            sign = np.sign(x[120:130, 8].mean())
            yaw, speed = sign * x[:, 8], np.abs(x[:, 4])
            row[side] = {"onset_peak": float(yaw[100:110].max()),
                         "turn": float(yaw[120:130].mean()),
                         "leftover": float(yaw[135:195].mean()),
                         "regained_speed": float(speed[130:160].mean())}
        rows.append(row)
    return rows


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def report(results: dict) -> str:
    """Markdown body: per action mode, ours beside native, then the speed per drive bin."""
    lines = [f"The {results['task']} expert of cost limit {results['limit']:g}, "
             f"{results['episodes']} episodes a side, each side's own layouts; native's "
             f"friction cone {results.get('native_cone', 'pyramidal')}.", ""]
    bins = [f"{lo:g}..{hi:g}" for lo, hi in itertools.pairwise(DRIVE_BINS)]
    for row in results["rows"]:
        o, t = row["ours"], row["theirs"]
        keys = [k for k in o if not isinstance(o[k], list)]
        lines += [f"## {row['policy']} action", "",
                  markdown_table(["statistic", "ours", "Safety-Gymnasium", "theirs / ours"],
                                 [[k, _fmt(o[k]), _fmt(t[k]),
                                   _fmt(t[k] / o[k]) if o[k] else "-"] for k in keys]), "",
                  markdown_table(["drive (a0 + a1) / 2", "share ours / SG",
                                  "speed toward body +y, ours / SG (m/s)"],
                                 [[b, f"{so:.3f} / {st:.3f}",
                                   f"{_fmt(vo)} / {_fmt(vt)}"]
                                  for b, so, st, vo, vt in zip(bins, o["share_by_drive"],
                                                              t["share_by_drive"],
                                                              o["speed_by_drive"],
                                                              t["speed_by_drive"],
                                                              strict=True)]), ""]
    if results.get("recovery"):
        keys = ("onset_peak", "turn", "leftover", "regained_speed")
        lines += ["## A turn and the recovery from it (open loop, ours / Safety-Gymnasium)", "",
                  markdown_table(["script", "onset peak yaw (rad/s)", "turn yaw",
                                  "leftover yaw, steps 135-195", "speed 130-160 (m/s)"],
                                 [[r["script"], *(f"{r['ours'][k]:.3f} / {r['theirs'][k]:.3f}"
                                                  for k in keys)]
                                  for r in results["recovery"]]), ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Command line: compare, write JSON and markdown."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="CarGoal1")
    p.add_argument("--limit", type=float, default=25.0)
    p.add_argument("--episodes", type=int, default=32)
    p.add_argument("--native-cone", choices=("pyramidal", "elliptic"), default="pyramidal")
    p.add_argument("--out", type=Path, default=Path("experiments/results/drive_stats.json"))
    args = p.parse_args(argv)
    command = "python -m experiments.drive_stats " + " ".join(
        sys.argv[1:] if argv is None else argv)
    cone = args.native_cone
    results = {"command": command, "machine": machine(), "task": args.task,
               "limit": args.limit, "episodes": args.episodes, "native_cone": cone,
               "rows": compare(args.task, args.limit, args.episodes, cone),
               "recovery": recovery(args.task, cone)}
    write_json(args.out, results)
    write_markdown(args.out.with_suffix(".md"), "How an expert drives in each simulator",
                   command, report(results))
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
