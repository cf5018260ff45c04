"""Which vase push rule makes a source expert pay in our level-2 Goal task what it pays natively?

    python -m experiments.vase_fit [--task CarGoal1] [--fits 0.5:2.5,1.0:2.5,1.5:2.0]
        [--episodes 128] [--seeds 0,1] [--native experiments/results/sim2sim_physics7_cg.json]
        [--out experiments/results/vase_fit.json]

Each fit is `RESTITUTION:CREEP_STEPS` of the disc vases for the task's robot
(`envs.goal.VASE_PUSH`: a pushed vase leaves at (1 + e) times the closing speed, and n is its
slowest decay in env steps; Goal rules 3: Car 1.5 and 2.0, Point 1.0 and 2.5). For every fit
and seed, the task's limit-25 expert (the snapshot `experiments.sim2sim.pick_expert` picks)
runs `--episodes` episodes in the level-2 target, with its mean action and with samples, in
our simulator only. The native side is read from a `sim2sim --parts transfer` result of the
same expert (`--native`, which needs the peer venv to make): per cost term, cost steps per
episode ours / native and their ratio native / ours; for the total cost, the ratio with its
95% bootstrap interval (`stats.ratio_interval`). Changes no default: a fit worth adopting is a
new Goal rules version (`envs.TASK_VERSIONS`), which reruns the Goal deployments and reports.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown
from experiments.sim2sim import TERMS, native, ours_policy, ours_random, pick_expert, target_task
from safecdt_jax.stats import ratio_interval


def native_rows(path: Path, task: str) -> dict[bool, dict]:
    """The native side of `task`'s expert in its level-2 target from a sim2sim result, keyed by
    `deterministic`."""
    rows = json.loads(path.read_text())["transfer"]
    found = {r["deterministic"]: r for r in rows
             if r["task"] == task and r["run_in"] == target_task(task)}
    if len(found) != 2:
        raise SystemExit(f"{path} has no transfer rows of {task} in {target_task(task)}")
    return found


ACTION = {True: "mean", False: "sampled", None: "random"}  # by `deterministic`


def native_random(run_in: str, episodes: int) -> dict:
    """Native `run_in` under uniform random actions, as a transfer row's native side (seed 0):
    mean return and cost, per-episode costs, and per term the mean cost steps."""
    t = native({"cmd": "policy", "task": run_in, "weights": None, "episodes": episodes,
                "seed": 0, "deterministic": False})
    return {"theirs_return": float(t["return"].mean()), "theirs_cost": float(t["cost"].mean()),
            "theirs_costs": t["cost"].tolist(),
            "terms": {k: {"theirs": float(t[k].mean())} for k in TERMS if k in t}}


def run_fit(task: str, restitution: float, creep: float, episodes: int, seed: int,
            deterministic: bool | None) -> dict[str, np.ndarray]:
    """Per-episode return, cost and cost steps per term of the expert (`deterministic` None:
    uniform random actions) in the level-2 target under one vase rule. The rule's constants are
    read when the episode is traced, so setting them on the module before the (fresh) trace is
    what changes the simulation."""
    from safecdt_jax import envs
    from safecdt_jax.envs import goal
    from safecdt_jax.experts.collect import snapshot_path

    robot = envs.make(task)[0].robot.name
    saved = goal.VASE_PUSH[robot]
    goal.VASE_PUSH[robot] = (restitution, creep)
    try:
        if deterministic is None:
            return ours_random(target_task(task), episodes, seed)
        return ours_policy(task, snapshot_path(task), pick_expert(task), episodes, seed,
                           deterministic, target_task(task))
    finally:
        goal.VASE_PUSH[robot] = saved


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal1")
    ap.add_argument("--fits", default="0.5:2.5,1.0:2.5,1.5:2.0")
    ap.add_argument("--episodes", type=int, default=128)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--native", type=Path,
                    default=Path("experiments/results/sim2sim_physics7_cg.json"))
    ap.add_argument("--out", type=Path, default=Path("experiments/results/vase_fit.json"))
    ap.add_argument("--random-episodes", type=int, default=0,
                    help="also uniform random actions, this many native episodes (0: none)")
    args = ap.parse_args(argv)
    natives = native_rows(args.native, args.task)
    if args.random_episodes:
        natives[None] = native_random(target_task(args.task), args.random_episodes)
    rows = []
    for fit in args.fits.split(","):
        e, creep = (float(x) for x in fit.split(":"))
        for seed in (int(s) for s in args.seeds.split(",")):
            for det in natives:
                ours = run_fit(args.task, e, creep, args.episodes, seed, det)
                theirs = natives[det]
                ci = ratio_interval(np.asarray(theirs["theirs_costs"]), ours["cost"])
                ratio = theirs["theirs_cost"] / float(ours["cost"].mean())
                terms = {k: {"ours": float(ours[k].mean()),
                             "theirs": theirs["terms"][k]["theirs"]}
                         for k in TERMS if k in theirs["terms"]}
                rows.append({"restitution": e, "creep_steps": creep, "seed": seed,
                             "deterministic": det, "return": float(ours["return"].mean()),
                             "theirs_return": theirs["theirs_return"],
                             "cost": float(ours["cost"].mean()),
                             "theirs_cost": theirs["theirs_cost"], "cost_ratio": ratio,
                             "cost_ratio_ci": list(ci), "terms": terms})
                print(f"e {e:g} creep {creep:g} seed {seed} {ACTION[det]}: "
                      f"cost {rows[-1]['cost']:.1f} / {theirs['theirs_cost']:.1f}",
                      file=sys.stderr, flush=True)
    command = "python -m experiments.vase_fit " + " ".join(sys.argv[1:] if argv is None
                                                         else argv)
    write_json(args.out, {"command": command, "machine": machine(), "task": args.task,
                          "episodes": args.episodes, "native": str(args.native), "rows": rows})
    short = {"cost_hazards": "hazards", "cost_vases_contact": "vase contact",
             "cost_vases_velocity": "vase velocity", "cost_out_of_boundary": "boundary"}
    names = [k for k in TERMS if k in rows[0]["terms"]]
    fmt = lambda o, t: f"{o:.1f} / {t:.1f} ({t / o:.2f})" if o else f"0 / {t:.1f}"
    body = markdown_table(
        ["e", "creep (steps)", "seed", "action", "return ours / native",
         "cost ours / native (ratio, 95% CI)", *[short[k] for k in names]],
        [[f"{r['restitution']:g}", f"{r['creep_steps']:g}", r["seed"],
          ACTION[r["deterministic"]],
          f"{r['return']:.1f} / {r['theirs_return']:.1f}",
          f"{r['cost']:.1f} / {r['theirs_cost']:.1f} ({r['cost_ratio']:.2f}, "
          f"{r['cost_ratio_ci'][0]:.2f}-{r['cost_ratio_ci'][1]:.2f})",
          *[fmt(r["terms"][k]["ours"], r["terms"][k]["theirs"]) for k in names]]
         for r in rows])
    body += ("\n\nCost steps per episode; ratios native / ours. The native side is one run per "
             f"action mode from `{args.native}` (seed 0 of its own layouts)"
             + (f"; random actions: {args.random_episodes} native episodes, run here"
                if args.random_episodes else "") + ".\n")
    write_markdown(args.out.with_suffix(".md"), f"Vase push rules: {args.task}'s expert in "
                   f"{target_task(args.task)}", command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
