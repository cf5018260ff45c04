"""Does the Car leave the Circle because its sliding wheels grip sideways too hard? (issue 48)

    python -m experiments.car_slide [--slide-follows-slip] [--car FIELD=VALUE ...]
        [--episodes 128] [--out PATH]

Runs, with our Car as it is or with `CarRobot.slide_follows_slip` (a sliding driven wheel's
force along its contact's own slip) and any `CarRobot` constants set with `--car`, beside
native Safety-Gymnasium (`experiments.sim2sim`'s
cached native runs):
- switch transients: from rest, straight (1, 1) for 15 steps, spin (1, -1) for 45, straight
  for 20, spin for 20;
  the yaw rate (gyro z, rad/s) and forward speed (-velocimeter y, m/s) in the first steps after
  each switch, mean of 8 layouts;
- the turning table (`sim2sim.turning`) on CarCircle1;
- the CarCircle1 limit-20 expert in CarCircle1 and CarCircle2, deterministic and stochastic
  (`sim2sim.transfer`): mean and median cost, return, and the cost ratio native / ours.
Writes JSON and markdown (default `experiments/results/car_slide[_slip].{json,md}`).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from benchmarks.common import machine, markdown_table, write_json, write_markdown

SWITCHES = [(1.0, 1.0)] * 15 + [(1.0, -1.0)] * 45 + [(1.0, 1.0)] * 20 + [(1.0, -1.0)] * 20
AFTER = (0, 1, 2, 3, 15, 16, 17, 60, 61, 62, 63, 80, 81, 82)  # steps just after each switch


def use_variant(slip: bool, constants: dict[str, float]) -> None:
    """Make every Car env of this process use the variant (before any env is built)."""
    from safecdt_jax import envs

    envs.CAR = dataclasses.replace(envs.CAR, slide_follows_slip=slip, **constants)
    envs._ENVS.clear()


def transients(task: str = "CarCircle1", episodes: int = 8) -> list[dict]:
    """Yaw rate and forward speed at the `AFTER` steps of `SWITCHES`, ours and native."""
    from experiments.sim2sim import native, ours_trace

    ours = ours_trace(task, episodes, len(SWITCHES), 0, SWITCHES)
    theirs = native({"cmd": "trace", "task": task, "episodes": episodes,
                     "steps": len(SWITCHES), "seed": 0, "actions": SWITCHES})["obs"]
    rows = []
    for t in AFTER:
        row = {"step": t, "action": list(SWITCHES[t])}
        for side, x in (("ours", ours), ("theirs", theirs)):
            row[f"{side}_yaw_rate"] = float(x[:, t, 8].mean())
            row[f"{side}_speed"] = float(-x[:, t, 4].mean())
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> None:
    from experiments.sim2sim import transfer, turning

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--slide-follows-slip", action="store_true")
    ap.add_argument("--car", action="append", default=[], metavar="FIELD=VALUE",
                    help="a CarRobot constant, e.g. yaw_scrub=0.01 (repeatable)")
    ap.add_argument("--episodes", type=int, default=128)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    slip = args.slide_follows_slip
    constants = {k: float(v) for k, v in (c.split("=", 1) for c in args.car)}
    use_variant(slip, constants)
    out = args.out or Path(f"experiments/results/car_slide{'_slip' if slip else ''}.json")
    trans = transients()
    turns = turning("CarCircle1")
    policy = transfer("CarCircle1", args.episodes, [20.0])
    command = "python -m experiments.car_slide " + " ".join(sys.argv[1:] if argv is None
                                                            else argv)
    write_json(out, {"command": command, "machine": machine(), "slide_follows_slip": slip,
                     "car": constants,
                     "transients": trans, "turning": turns, "transfer": policy})
    f2 = lambda x: f"{x:.2f}"
    body = "Switch transients (8 layouts):\n\n" + markdown_table(
        ["step", "action", "yaw ours / native", "speed ours / native"],
        [[r["step"], str(tuple(r["action"])), f"{f2(r['ours_yaw_rate'])} / "
          f"{f2(r['theirs_yaw_rate'])}", f"{f2(r['ours_speed'])} / {f2(r['theirs_speed'])}"]
         for r in trans])
    body += "\n\nTurning (steps 100-500):\n\n" + markdown_table(
        ["script", "speed ours / native", "yaw ours / native"],
        [[r["script"], f"{f2(r['ours_speed'])} / {f2(r['theirs_speed'])}",
          f"{f2(r['ours_yaw_rate'])} / {f2(r['theirs_yaw_rate'])}"] for r in turns])
    body += "\n\nThe CarCircle1 limit-20 expert:\n\n" + markdown_table(
        ["run in", "actions", "return ours / native", "cost ours / native (median)",
         "native / ours cost (95% CI)"],
        [[r["run_in"], "mean" if r["deterministic"] else "sampled",
          f"{f2(r['ours_return'])} / {f2(r['theirs_return'])}",
          f"{r['ours_cost']:.1f} / {r['theirs_cost']:.1f} ({r['ours_median_cost']:.0f} / "
          f"{r['theirs_median_cost']:.0f})",
          f"{r['cost_ratio']:.2f} ({r['cost_ratio_ci'][0]:.2f}-{r['cost_ratio_ci'][1]:.2f})"]
         for r in policy])
    write_markdown(out.with_suffix(".md"), "Car sliding-wheel model on CarCircle "
                   f"({'slip-directed' if slip else 'as is'}"
                   f"{''.join(f', {k} {v:g}' for k, v in constants.items())})", command, body)
    print(out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
