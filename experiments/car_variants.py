"""The Car experts in our simulator under variants of the Car, beside native's numbers (issue 48).

    python -m experiments.car_variants [--tasks CarGoal1:25,CarCircle1:5] [--episodes 64]
        [--variant NAME=FIELD:VALUE,FIELD:VALUE ...] [--fit NAME=car_fit_result.json ...]
        [--native experiments/results/sim2sim_goal3_cg.json ...] [--on car_sysid.json]
        [--cells source,target] [--modes mean,sampled]
        [--out experiments/results/car_variants.json]

A candidate Car model (other `CarRobot` constants, another `friction_cone`) is only worth a
physics version if the experts that decide the data drive in it as they drive in native
Safety-Gymnasium. Per source task and cost limit (`--tasks`), the task's expert
(`sim2sim.pick_expert`, fixed: trained on the current physics) runs in the source task and its
level-2 target, mean and sampled actions, `--episodes` episodes on the same keys under every
variant: physics as it is ("current"), each `--variant` (fields and values) and each `--fit`
(the constants, cone and saturation power of an `experiments.car_fit` result). The native
columns are read from sim2sim transfer results (`--native`, rows with the same expert limit,
task and action mode), so nothing native reruns. `--on` applies every `--variant` on top of a
fit's constants; `--cells` and `--modes` pick the run-in tasks and action modes (the rare
CarCircle1 escapes want hundreds of episodes per cell). Our simulator only; writes JSON and
markdown.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown
from experiments.sim2sim import ours_policy, pick_expert, target_task

NATIVE = tuple(f"experiments/results/{name}.json" for name in (
    "sim2sim_goal3_cg", "sim2sim_physics6_experts_cc", "sim2sim_cc1_512_limit5",
    "sim2sim_cc1_512_limit20"))


def parse_variant(text: str) -> tuple[str, dict]:
    """`NAME=FIELD:VALUE,FIELD:VALUE` -> (name, {field: value}); values are floats except
    `friction_cone`, and tuples of floats where the value holds "/" (`wheel_hop:0.75/11/10`).
    SystemExit naming the field if it is not a `CarRobot` field."""
    from safecdt_jax.envs.robots import CarRobot

    name, _, spec = text.partition("=")
    fields = {f.name for f in dataclasses.fields(CarRobot)}
    out = {}
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition(":")
        if key not in fields:
            raise SystemExit(f"--variant {name}: {key!r} is not a CarRobot field")
        if key == "friction_cone":
            out[key] = value
        elif "/" in value:
            out[key] = tuple(float(v) for v in value.split("/"))
        else:
            out[key] = float(value)
    return name, out


def fit_variant(path: Path) -> dict:
    """The `CarRobot` fields an `experiments.car_fit` result sets."""
    result = json.loads(Path(path).read_text())
    return {**result["constants"], "saturation_power": result["saturation_power"],
            "friction_cone": result.get("cone", "elliptic")}


def native_rows(paths) -> dict[tuple, dict]:
    """(expert task, limit, run in, deterministic) -> native return, cost and goals, from the
    transfer rows of sim2sim results (a later file's row replaces an earlier one's)."""
    out = {}
    for path in paths:
        for row in json.loads(Path(path).read_text()).get("transfer", []):
            key = (row["task"], float(row["limit"]), row["run_in"], row["deterministic"])
            out[key] = {k: row[f"theirs_{k}"] for k in ("return", "cost", "goals")} | {
                "median_cost": row["theirs_median_cost"], "episodes": row["episodes"]}
    return out


def variant_rows(task: str, limit: float, episodes: int, variants: dict[str, dict],
                 cells: tuple[str, ...] = ("source", "target"),
                 modes: tuple[str, ...] = ("mean", "sampled")) -> list[dict]:
    """Per variant, run-in task (`cells`: the source task, its level-2 target) and action mode
    (`modes`): our mean return, cost, median cost, goals."""
    from safecdt_jax import envs
    from safecdt_jax.experts.collect import snapshot_path

    index, robot = pick_expert(task, limit), envs.make(task)[0].robot
    rows = []
    for name, fields in variants.items():
        variant = dataclasses.replace(robot, **fields)
        for run_in in [{"source": task, "target": target_task(task)}[c] for c in cells]:
            for det in [mode == "mean" for mode in modes]:
                o = ours_policy(task, snapshot_path(task), index, episodes, 0, det, run_in,
                                robot=variant)
                rows.append({"variant": name, "task": task, "limit": limit, "run_in": run_in,
                             "deterministic": det, "return": float(o["return"].mean()),
                             "cost": float(o["cost"].mean()),
                             "median_cost": float(np.median(o["cost"])),
                             "goals": float(o["goals"].mean())})
    return rows


def report(rows: list[dict], native: dict) -> str:
    """Markdown: one row per variant and cell, native's numbers beside."""
    table = []
    for r in rows:
        t = native.get((r["task"], r["limit"], r["run_in"], r["deterministic"]))
        nat = (f"{t['return']:.1f} / {t['cost']:.1f} / {t['median_cost']:.1f} / {t['goals']:.1f}"
               if t else "-")
        ratio = f"{t['cost'] / max(r['cost'], 1e-9):.2f}" if t else "-"
        table.append([r["variant"], f"{r['task']} {r['limit']:g}", r["run_in"],
                      "mean" if r["deterministic"] else "sampled",
                      f"{r['return']:.1f} / {r['cost']:.1f} / {r['median_cost']:.1f} / "
                      f"{r['goals']:.1f}", nat, ratio])
    return markdown_table(["variant", "expert", "run in", "policy",
                           "ours: return / cost / median / goals", "native (sim2sim)",
                           "cost native / ours"], table)


def main(argv: list[str] | None = None) -> None:
    """Command line: run every variant, write JSON and markdown."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="CarGoal1:25,CarCircle1:5")
    ap.add_argument("--episodes", type=int, default=64)
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--fit", action="append", default=[], metavar="NAME=PATH")
    ap.add_argument("--native", action="append", default=[])
    ap.add_argument("--on", type=Path, default=None, metavar="PATH",
                    help="a car_fit / car_sysid result every --variant is applied on top of")
    ap.add_argument("--cells", default="source,target", help="source, target or both")
    ap.add_argument("--modes", default="mean,sampled", help="mean, sampled or both")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/car_variants.json"))
    args = ap.parse_args(argv)
    cells, modes = tuple(args.cells.split(",")), tuple(args.modes.split(","))
    if not set(cells) <= {"source", "target"} or not set(modes) <= {"mean", "sampled"}:
        raise SystemExit(f"--cells from source,target and --modes from mean,sampled; got "
                         f"{args.cells!r}, {args.modes!r}")
    base = fit_variant(args.on) if args.on else {}
    variants = {"current": {}}
    variants |= {name: base | fields for name, fields in map(parse_variant, args.variant)}
    for item in args.fit:
        name, _, path = item.partition("=")
        variants[name] = fit_variant(Path(path))
    rows = []
    for spec in args.tasks.split(","):
        task, _, limit = spec.partition(":")
        if not task.startswith("Car"):
            raise SystemExit(f"--tasks: Car tasks only, got {task}")
        rows += variant_rows(task, float(limit), args.episodes, variants, cells, modes)
    native = native_rows(args.native or NATIVE)
    command = "python -m experiments.car_variants " + " ".join(
        sys.argv[1:] if argv is None else argv)
    write_json(args.out, {"command": command, "machine": machine(), "variants": variants,
                          "episodes": args.episodes, "rows": rows})
    body = (f"The experts (fixed) in our simulator under each Car variant, {args.episodes} "
            "episodes on the same keys; native's numbers from the sim2sim results "
            f"({', '.join(args.native or NATIVE)}).\n\n" + report(rows, native))
    write_markdown(args.out.with_suffix(".md"), "The Car experts under Car variants", command,
                   body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
