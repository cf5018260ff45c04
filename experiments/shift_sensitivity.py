"""How far does a small change of our own dynamics move an expert's cost? The yardstick for
sim-to-sim ratios.

    python -m experiments.shift_sensitivity [--tasks CarGoal1,CarCircle1] [--limits 25;5,20]
        [--episodes 128] [--scale 0.1] [--out experiments/results/shift_sensitivity.json]

An expert trained in one simulator and run in another pays for every difference between them,
and a policy tuned to its own dynamics (a Circle expert hugging the boundary) pays for any
difference at all. So before a native / ours cost ratio of 1.7 is read as a fault of our
physics, this script measures what our own physics does to the same expert when one dynamics
scale (`envs.dynamics`: gear, friction, damping, mass) moves by +-`scale` (a 10% change of one
constant is well inside what the Car's calibration can resolve). Per source task, for each
expert limit (`--limits`, `;` between tasks; default each task's sim2sim limit) and action mode
(mean, sampled), in the source task and its level-2 target: return and cost of the nominal
dynamics, of the nominal dynamics on other keys (the sampling noise of `--episodes` episodes)
and of each shift on the nominal keys (paired: the same layouts and policy noise), with the
ratio shifted / nominal and its 95% bootstrap interval (`stats.ratio_interval`). Our simulator
only; writes JSON and markdown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown
from experiments.sim2sim import LIMIT, expert_policy, ours_episodes, pick_expert, target_task
from safecdt_jax.envs.dynamics import DYNAMICS_FIELDS, shift_label
from safecdt_jax.stats import ratio_interval

NOISE = "nominal, other keys"


def shifts_of(scale: float) -> list[dict[str, float]]:
    """The nominal dynamics, then each dynamics field scaled by 1 - `scale` and 1 + `scale`."""
    if not 0 < scale < 1:
        raise SystemExit(f"--scale must lie in (0, 1), got {scale}")
    return [{}] + [{field: round(1 + sign * scale, 6)} for field in DYNAMICS_FIELDS
                   for sign in (-1, 1)]


def sensitivity_rows(task: str, limit: float, episodes: int, scale: float,
                     seed: int = 0) -> list[dict]:
    """One row per (run_in, action mode, dynamics): mean return, cost and median cost, and the
    return and cost ratios to the nominal row with the cost ratio's 95% interval."""
    from safecdt_jax.experts.collect import snapshot_path

    index = pick_expert(task, limit)
    shifts = shifts_of(scale)
    rows = []
    for run_in in (task, target_task(task)):
        for det in (True, False):
            policy = expert_policy(snapshot_path(task), index, det)
            out = ours_episodes(run_in, policy, episodes, seed, shifts)
            other = ours_episodes(run_in, policy, episodes, seed + 1)
            runs = [(shift_label(s), out["return"][i], out["cost"][i])
                    for i, s in enumerate(shifts)]
            runs.insert(1, (NOISE, other["return"], other["cost"]))
            nominal_return, nominal_cost = runs[0][1], runs[0][2]
            for label, ret, cost in runs:
                rows.append({
                    "task": task, "limit": limit, "snapshot": index, "run_in": run_in,
                    "deterministic": det, "dynamics": label, "episodes": episodes,
                    "return": float(ret.mean()), "cost": float(cost.mean()),
                    "median_cost": float(np.median(cost)),
                    "return_ratio": float(ret.mean() / nominal_return.mean()),
                    "cost_ratio": float(cost.mean() / max(nominal_cost.mean(), 1e-9)),
                    "cost_ratio_ci": list(ratio_interval(cost, nominal_cost)),
                    "costs": cost.tolist()})
            print(f"{task} limit {limit:g} in {run_in} {'mean' if det else 'sampled'}: "
                  f"nominal cost {nominal_cost.mean():.1f}", file=sys.stderr, flush=True)
    return rows


def report(rows: list[dict]) -> str:
    """The markdown table: one line per row, ratios to the nominal row of its block."""
    return markdown_table(
        ["expert", "run in", "action", "dynamics", "return (ratio)", "cost (ratio, 95% CI)",
         "median cost"],
        [[f"{r['task']} {r['limit']:g}", r["run_in"], "mean" if r["deterministic"] else "sampled",
          r["dynamics"], f"{r['return']:.1f} ({r['return_ratio']:.2f})",
          f"{r['cost']:.1f} ({r['cost_ratio']:.2f}, {r['cost_ratio_ci'][0]:.2f}-"
          f"{r['cost_ratio_ci'][1]:.2f})", f"{r['median_cost']:.1f}"] for r in rows])


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="CarGoal1,CarCircle1")
    ap.add_argument("--limits", default="",
                    help="per task, comma-separated limits; `;` between tasks (default: 25 / 20)")
    ap.add_argument("--episodes", type=int, default=128)
    ap.add_argument("--scale", type=float, default=0.1)
    ap.add_argument("--out", type=Path,
                    default=Path("experiments/results/shift_sensitivity.json"))
    args = ap.parse_args(argv)
    tasks = args.tasks.split(",")
    limits = args.limits.split(";") if args.limits else [""] * len(tasks)
    if len(limits) != len(tasks):
        raise SystemExit(f"--limits has {len(limits)} groups for {len(tasks)} tasks")
    rows = []
    for task, group in zip(tasks, limits, strict=True):
        default = LIMIT["Goal" if "Goal" in task else "Circle"]
        for limit in [float(x) for x in group.split(",")] if group else [default]:
            rows += sensitivity_rows(task, limit, args.episodes, args.scale)
    command = "python -m experiments.shift_sensitivity " + " ".join(
        sys.argv[1:] if argv is None else argv)
    write_json(args.out, {"command": command, "machine": machine(), "scale": args.scale,
                          "episodes": args.episodes, "rows": rows})
    body = report(rows) + (
        "\n\nOur simulator only. Each shift runs the nominal row's keys (the same layouts and "
        "policy noise); the 'nominal, other keys' row is the same dynamics on other keys, so "
        "its ratio shows what sampling alone moves. Ratios shifted / nominal.\n")
    write_markdown(args.out.with_suffix(".md"), "What a 10% change of our own dynamics does to "
                   "the experts' cost" if args.scale == 0.1 else "Dynamics sensitivity",
                   command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
