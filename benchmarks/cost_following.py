"""Does the pretrained CDT's cost follow its cost target? Tasks x pretraining seeds, `cpu` defaults.

    python -m benchmarks.cost_following [--tasks CarGoal1,CarCircle1,PointCircle1]
        [--seeds 0,1,2,3] [--episodes 20] [--out benchmarks/results/cost_following.json]

For each source task: the default source data (`ensure_source_data`: the committed experts'
snapshots, grid-filtered as DSRL does), a `cpu`-preset CDT pretrained with each seed at the
defaults, then `episodes` episodes in the source task at cost targets 10/20/40/80 and return
targets of half and all of the reference return R_ref. A (task, seed, return target) passes when
the mean cost rises with the cost target (Spearman >= 0.8) and lies below the data's median
episode cost at target 20. Results go to the JSON after every (task, seed), atomically, and a
rerun skips what is there, so an interrupted run continues.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from benchmarks.common import machine, markdown_table, write_json

COST_TARGETS = (10.0, 20.0, 40.0, 80.0)
RETURN_RATIOS = (0.5, 1.0)


def run_one(task: str, seed: int, episodes: int) -> dict:
    """Pretrain (or reuse) seed `seed`'s CDT on `task`'s default data and evaluate it."""
    from safecdt_jax import paths
    from safecdt_jax.analysis.evaluate import evaluate_checkpoint
    from safecdt_jax.data import summarize_dataset
    from safecdt_jax.experts.collect import ensure_source_data
    from safecdt_jax.pretrain.checkpoint import read_meta
    from safecdt_jax.pretrain.run import ensure_checkpoint

    start = time.perf_counter()
    data = ensure_source_data(task)
    median = summarize_dataset(data)["cost_median"]
    out = paths.cache_root() / "checkpoints" / f"{task}-cpu-seed{seed}"
    ckpt = ensure_checkpoint(data, task, "cpu", seed=seed, out=out, overwrite=True,
                             progress=False)
    r_ref = float(read_meta(ckpt)["dataset"]["reference_return"])
    targets = [(ratio * r_ref, c) for ratio in RETURN_RATIOS for c in COST_TARGETS]
    summary = evaluate_checkpoint(ckpt, task, targets, episodes, seed=1000 + seed,
                                  data_median=median)
    rows = []
    for ratio, follow in zip(RETURN_RATIOS, summary["cost_following"], strict=True):
        at = [r for r in summary["rows"] if r["target_return"] == follow["target_return"]]
        costs = [r["mean_cost"] for r in at]
        rho = follow["spearman"]
        below = costs[COST_TARGETS.index(20.0)] < median
        rows.append({"return_ratio": ratio, "target_return": follow["target_return"],
                     "mean_costs": costs, "mean_returns": [r["mean_return"] for r in at],
                     "spearman": rho, "below_median_at_20": bool(below),
                     "passes": bool(rho is not None and rho >= 0.8 and below)})
    from safecdt_jax.data.collect import file_attrs

    attrs = file_attrs(data) or {}
    return {"task": task, "seed": seed, "data_median_cost": median, "reference_return": r_ref,
            "data": {k: attrs.get(k) for k in ("behaviour", "expert_collector_version",
                                               "snapshot_sha256", "seed")},
            "episodes": episodes, "rows": rows, "seconds": time.perf_counter() - start}


def table(results: list[dict]) -> str:
    """One markdown row per (task, seed, return target), then a pass count per task."""
    head = ["task", "seed", "return target", *[f"cost @ {c:g}" for c in COST_TARGETS],
            "Spearman", "data median", "< median @ 20", "pass"]
    rows = []
    for res in results:
        for r in res["rows"]:
            rho = "n/a" if r["spearman"] is None else f"{r['spearman']:.2f}"
            rows.append([res["task"], res["seed"], f"{r['return_ratio']:g} R_ref",
                         *[f"{c:.1f}" for c in r["mean_costs"]], rho,
                         f"{res['data_median_cost']:.1f}", "yes" if r["below_median_at_20"]
                         else "no", "PASS" if r["passes"] else "fail"])
    lines = [markdown_table(head, rows), ""]
    for task in dict.fromkeys(r["task"] for r in results):
        mine = [r for r in results if r["task"] == task]
        for ratio in RETURN_RATIOS:
            n = sum(row["passes"] for r in mine for row in r["rows"]
                    if row["return_ratio"] == ratio)
            lines.append(f"- {task}, return target {ratio:g} R_ref: {n} of {len(mine)} seeds "
                         f"pass")
    return "\n".join(lines)


def main() -> None:
    """Runs the missing (task, seed) cells, rewriting the JSON after each; prints the table."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="CarGoal1,CarCircle1,PointCircle1")
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/cost_following.json"))
    args = ap.parse_args()
    old = json.loads(args.out.read_text()) if args.out.exists() else {"results": []}
    from safecdt_jax.experts.collect import EXPERT_COLLECTOR_VERSION

    # Cells of other data (an older collector) are measured again.
    results = [r for r in old["results"] if r["episodes"] == args.episodes and r.get(
        "data", {}).get("expert_collector_version") == EXPERT_COLLECTOR_VERSION]
    done = {(r["task"], r["seed"]) for r in results}
    for task in args.tasks.split(","):
        for seed in (int(s) for s in args.seeds.split(",")):
            if (task, seed) in done:
                continue
            results.append(run_one(task, seed, args.episodes))
            write_json(args.out, {"machine": machine(), "results": results,
                                  "command": "python -m benchmarks.cost_following"})
            print(f"{task} seed {seed}: {results[-1]['seconds']:.0f} s", flush=True)
    text = table(results)
    args.out.with_suffix(".md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
