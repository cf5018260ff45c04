"""The Car's caster ball, ours against Safety-Gymnasium's, under scripted drives.

    python -m experiments.caster_ball [--task CarCircle1] [--steps 400] [--layouts 4]
        [--out experiments/results/caster_ball.json]

Each drive (held torques, switching drives, uniform random actions; `DRIVES`) runs open-loop
from rest in both simulators, `layouts` resets each. Over steps 100 onward it reports the
ball's spin relative to the chassis, in the chassis frame (the ballquat sensor's rotation
times the ballangvel sensor's reading, rad/s): the percentiles of its roll about the lateral
axis, the lag-1 autocorrelation of that roll (0: a fresh rate each step), the std of its spin
about the other two axes, and the forward speed. Native MuJoCo's ball rolls steadily at low
speed and stick-slips above about 6 rad/s; physics 7's constants (`CarRobot.caster_*`) were
fitted to these rows. Needs the peer venv (`python -m benchmarks.peers.setup`). Writes JSON
and markdown.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown

PERCENTILES = (5, 25, 50, 75, 95)
WARMUP = 100  # steps from rest before the statistics start


def drives(steps: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Open-loop action scripts [steps, 2] by name. The Car's torque saturates at |a| = 0.02,
    so a = 1 is full torque; 'switch p' drives the left wheel forward and the right one
    backward with probability p each step (an expert's loop at p = 0.35)."""
    rng = np.random.default_rng(seed)
    held = {f"held {a:g}": np.full((steps, 2), a) for a in (0.005, 0.01, 0.015, 1.0)}
    switch = {f"switch p = {p:g}": np.stack([np.ones(steps), np.where(
        rng.random(steps) < p, -1.0, 1.0)], axis=1) for p in (0.15, 0.35)}
    return {**held, **switch, "uniform random": rng.uniform(-1.0, 1.0, (steps, 2))}


def ball_stats(obs: np.ndarray) -> dict[str, float | list[float]]:
    """Statistics of the ball's chassis-frame spin from Car observations [episodes, steps, dim]
    (sensor order: ..., velocimeter 3-5, ..., ballangvel 12-14, ballquat 15-23)."""
    o = obs[:, WARMUP:]
    rot = o[..., 15:24].reshape(*o.shape[:2], 3, 3)
    spin = np.einsum("etij,etj->eti", rot, o[..., 12:15])
    roll = spin[..., 0]
    lag1 = [np.corrcoef(r[:-1], r[1:])[0, 1] for r in roll if r.std() > 1e-6]
    return {"speed": float(-o[..., 4].mean()),
            "roll_pct": np.percentile(roll, PERCENTILES).round(2).tolist(),
            "lag1": float(np.mean(lag1)) if lag1 else float("nan"),
            "std_y": float(spin[..., 1].std()), "std_z": float(spin[..., 2].std())}


def compare(task: str, steps: int, layouts: int) -> list[dict]:
    """One row per drive and side: `ball_stats` of ours and of native Safety-Gymnasium."""
    from experiments.sim2sim import native, ours_trace

    rows = []
    for name, script in drives(steps).items():
        script = script.tolist()
        ours = ours_trace(task, layouts, steps, 0, script)
        theirs = native({"cmd": "trace", "task": task, "episodes": layouts, "steps": steps,
                         "seed": 0, "actions": script})["obs"]
        rows += [{"drive": name, "side": side, **ball_stats(o)}
                 for side, o in (("ours", ours), ("Safety-Gymnasium", theirs))]
    return rows


def main(argv: list[str] | None = None) -> None:
    """Command line: measure, print the table, write JSON and markdown."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarCircle1")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--layouts", type=int, default=4)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/caster_ball.json"))
    args = ap.parse_args(argv)
    if not args.task.startswith("Car"):
        raise SystemExit(f"--task: the caster ball is the Car's, got {args.task}")
    if args.steps <= WARMUP + 2:
        raise SystemExit(f"--steps must exceed {WARMUP + 2}, got {args.steps}")
    command = "python -m experiments.caster_ball " + " ".join(
        sys.argv[1:] if argv is None else argv)
    rows = compare(args.task, args.steps, args.layouts)
    write_json(args.out, {"command": command, "machine": machine(), "task": args.task,
                          "rows": rows})
    body = (f"{args.task}, {args.layouts} layouts, steps {WARMUP}-{args.steps}: the ball's roll "
            "about the chassis' lateral axis (rad/s, percentiles "
            f"{'/'.join(map(str, PERCENTILES))}), its lag-1 autocorrelation, and the std of its "
            "spin about the other two axes.\n\n")
    body += markdown_table(
        ["drive", "side", "speed (m/s)", "roll percentiles", "lag-1", "std y / z"],
        [[r["drive"], r["side"], f"{r['speed']:.2f}", " / ".join(f"{v:.1f}" for v in
                                                                  r["roll_pct"]),
          f"{r['lag1']:.2f}", f"{r['std_y']:.2f} / {r['std_z']:.2f}"] for r in rows])
    write_markdown(args.out.with_suffix(".md"), "The caster ball, ours and Safety-Gymnasium's",
                   command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
