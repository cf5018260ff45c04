"""Does the pretrained CDT's cost follow its cost target? Tasks x pretraining seeds, `cpu` defaults.

    python -m experiments.cost_following [--tasks CarGoal1,CarCircle1,PointCircle1]
        [--seeds 0,1,2,3] [--episodes 20] [--token-bins N] [--token-rates]
        [--constant-targets] [--labels episode|policy|auto] [--scale-actions]
        [--standardize-obs] [--relabel-percent P] [--c0 C] [--actions executed|sampled]
        [--no-stochastic-actions] [--returns ratios|frontier] [--set FIELD=VALUE ...]
        [--out PATH]

For each source task: the default source data (`ensure_source_data`: the committed experts'
snapshots, grid-filtered as DSRL does), a `cpu`-preset CDT pretrained with each seed at the
defaults, then `episodes` episodes in the source task at cost targets 10/20/40/80 and return
targets of half and all of the reference return R_ref. A (task, seed, return target) passes when
the mean cost rises with the cost target (Spearman >= 0.8) and, at target 20, lies below the
data's median episode cost, or below 20 itself where the median is lower (PointCircle1's expert
data have median 0: 60% of their episodes cost nothing, and no policy's mean goes below 0).
The flags after `--episodes` pretrain a variant of the `cpu` preset (its options:
docs/METHOD.md sections 0 and 8); `--actions executed` uses source data that record the
experts' executed actions instead of their sampled ones (section 8). The CDT acts with samples
of its Gaussian head, as every command does by default since 2026-12-07 (section 1; the cells
are named `cpu+stochastic_actions=True`); `--no-stochastic-actions` evaluates the same
checkpoints acting with its mean (the cells named `cpu`, the criterion's until then).
`--returns frontier` evaluates the same checkpoints with each cost target c paired with its own
return, the data's frontier at c (the 90th percentile of the returns of the episodes costing at
most c), as OSRL pairs each cost target with a return the data show feasible, instead of one
ratio of R_ref for all four (section 9). `--set steps=20000` (repeatable) overrides any other
`PretrainConfig` or `CDTConfig` field of the `cpu` preset. Each variant's cells are kept apart.
Results go to the JSON after every (task, seed), atomically, and a rerun skips what is
there, so an interrupted run continues. The JSON (default
`experiments/results/cost_following.json`, its table beside it as `.md`) holds one episode
count: a run at another `--episodes` measures its cells afresh and drops those of the old
count from the file (at 20 a cell's Spearman often hangs on means closer than their noise;
the committed file is at 50, docs/METHOD.md section 9).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json
from safecdt_jax.analysis.evaluate import ACTION_MODES, DEFAULT_ACTION_MODE
from safecdt_jax.paths import DEFAULT_ACTIONS
from safecdt_jax.stats import doubling_slope, frontier_returns

COST_TARGETS = (10.0, 20.0, 40.0, 80.0)
RETURN_RATIOS = (0.5, 1.0)


def data_fingerprint(task: str, actions: str = DEFAULT_ACTIONS) -> tuple[str, str]:
    """The action recording the file of `task`'s source data asked with `actions` holds (the
    Point's experts record 'executed' whatever is asked; files without the attribute are
    'executed') and its fingerprint (`dataset_record`), collecting it if needed: a cell
    measured on other data is stale. Cells are keyed by their recorded mode, so this is the
    key their fingerprint is checked under."""
    from safecdt_jax.data import load_dataset
    from safecdt_jax.data.collect import file_attrs
    from safecdt_jax.experts.collect import ensure_source_data
    from safecdt_jax.pretrain.run import dataset_record

    path = ensure_source_data(task, actions=actions)
    recorded = (file_attrs(path) or {}).get("actions") or "executed"
    return recorded, dataset_record(path, load_dataset(path))["fingerprint"]


@functools.cache
def committed_snapshot_sha256(task: str) -> str:
    """SHA-256 of `task`'s committed expert snapshots, read once per process."""
    from safecdt_jax.experts.collect import snapshot_path, snapshot_sha256

    return snapshot_sha256(snapshot_path(task))


def same_experts(cell: dict) -> bool:
    """Whether a result cell's data came from the task's committed expert snapshots (cells of
    retrained experts are stale, a second guard beside the data fingerprint). Cells that
    record no snapshot hash pass."""
    sha = cell.get("data", {}).get("snapshot_sha256")
    return sha is None or sha == committed_snapshot_sha256(cell["task"])


def parse_overrides(items: list[str]) -> dict:
    """`["steps=20000", "embed_dim=96"]` -> `{"steps": 20000, "embed_dim": 96}` for fields of
    `PretrainConfig` or `CDTConfig` (`validate.field_overrides`)."""
    from safecdt_jax.model import CDTConfig
    from safecdt_jax.pretrain.config import PretrainConfig
    from safecdt_jax.validate import field_overrides

    return field_overrides(items, PretrainConfig, CDTConfig)


def bar_at_20(median: float) -> float:
    """The cost the model must stay below at target 20: the data's median, or 20 if lower."""
    return max(float(median), COST_TARGETS[1])


def variant_name(variant: dict) -> str:
    """A short name of a `cpu` variant ({} -> "cpu"), e.g. "cpu+token_bins=16+labels=policy"."""
    return "+".join(["cpu", *(f"{k}={v}" for k, v in sorted(variant.items()))])


EVALUATION_ONLY = ("stochastic_actions", "returns")


def trained_variant(variant: dict) -> dict:
    """The part of a variant that pretraining sees: without the evaluation-only choices, so a
    variant that only acts otherwise reuses the same checkpoint."""
    return {k: v for k, v in variant.items() if k not in EVALUATION_ONLY}


def run_one(task: str, seed: int, episodes: int, variant: dict | None = None) -> dict:
    """Pretrain (or reuse) seed `seed`'s CDT on `task`'s default data and evaluate it.

    `variant`: `actions` (the source data's action recording), `PretrainConfig` fields (e.g.
    `labels`, `relabel_percent`, `c0`) and `CDTConfig` fields (the rest: `token_bins`,
    `token_rates`, `constant_targets`) that differ from the `cpu` preset. `stochastic_actions`
    and `returns` ("frontier": each cost target at the data's frontier return) are evaluation
    choices: they share the checkpoint of the variant without them."""
    from safecdt_jax import paths
    from safecdt_jax.analysis.evaluate import evaluate_checkpoint, spearman
    from safecdt_jax.data import load_dataset, summarize_dataset
    from safecdt_jax.experts.collect import ensure_source_data
    from safecdt_jax.pretrain.checkpoint import read_meta
    from safecdt_jax.pretrain.config import PretrainConfig
    from safecdt_jax.pretrain.run import ensure_checkpoint

    start = time.perf_counter()
    variant = dict(variant or {})
    data = ensure_source_data(task, actions=variant.get("actions", DEFAULT_ACTIONS))
    dataset = load_dataset(data)  # read once: the summary and the frontier share it
    median = summarize_dataset(dataset)["cost_median"]
    pre_fields = {f.name for f in dataclasses.fields(PretrainConfig)}
    pre = {k: v for k, v in variant.items() if k in pre_fields}
    model = {k: v for k, v in trained_variant(variant).items() if k not in pre and k != "actions"}
    name = variant_name(variant)
    trained = variant_name(trained_variant(variant))
    out = paths.cache_root() / "checkpoints" / f"{task}-{trained}-seed{seed}"
    ckpt = ensure_checkpoint(data, task, "cpu", seed=seed, out=out, overwrite=True,
                             progress=False, model_overrides=model, pretrain_overrides=pre)
    r_ref = float(read_meta(ckpt)["dataset"]["reference_return"])
    if variant.get("returns") == "frontier":
        groups = {"frontier": [(r, c) for r, c in zip(
            frontier_returns(dataset.rewards.sum(1), dataset.costs.sum(1), COST_TARGETS),
            COST_TARGETS, strict=True)]}
    else:
        groups = {ratio: [(ratio * r_ref, c) for c in COST_TARGETS] for ratio in RETURN_RATIOS}
    targets = [t for group in groups.values() for t in group]
    summary = evaluate_checkpoint(ckpt, task, targets, episodes, seed=1000 + seed,
                                  data_median=median,
                                  stochastic_actions=variant.get("stochastic_actions"))
    rows = []
    for g, (label, group) in enumerate(groups.items()):
        index = list(range(g * len(COST_TARGETS), (g + 1) * len(COST_TARGETS)))
        at = [summary["rows"][i] for i in index]
        costs = [r["mean_cost"] for r in at]
        rho = spearman(COST_TARGETS, costs)
        rho = None if np.isnan(rho) else rho
        below = costs[COST_TARGETS.index(20.0)] < bar_at_20(median)
        episode_costs = np.asarray(summary["costs"])[index]
        rows.append({"return_ratio": label, "target_return": group[0][0],
                     "target_returns": [r for r, _ in group],
                     "mean_costs": costs, "mean_returns": [r["mean_return"] for r in at],
                     "episode_costs": episode_costs.round(3).tolist(),
                     "slope_per_doubling": doubling_slope(COST_TARGETS, episode_costs,
                                                          seed=seed),
                     "spearman": rho, "below_median_at_20": bool(below),
                     "passes": bool(rho is not None and rho >= 0.8 and below)})
    from safecdt_jax.data.collect import file_attrs

    attrs = file_attrs(data) or {}
    return {"task": task, "seed": seed, "variant": name, "data_median_cost": median,
            "data_fingerprint": read_meta(ckpt)["dataset"]["fingerprint"],
            "reference_return": r_ref,
            "data": {k: attrs.get(k) for k in ("behaviour", "expert_collector_version",
                                               "actions", "snapshot_sha256", "seed")},
            "episodes": episodes, "rows": rows, "seconds": time.perf_counter() - start}


def _slope(row: dict) -> str:
    s = row.get("slope_per_doubling")
    return "n/a" if s is None else f"{s['slope']:+.1f} ({s['low']:+.1f}, {s['high']:+.1f})"


def return_label(row: dict) -> str:
    """A row's return target as the table prints it: "0.5 R_ref", or the frontier's returns."""
    if row["return_ratio"] == "frontier":
        return "frontier " + "/".join(f"{r:.1f}" for r in row["target_returns"])
    return f"{row['return_ratio']:g} R_ref"


def table(results: list[dict]) -> str:
    """One markdown row per (task, seed, return target), then a pass count per task."""
    head = ["task", "variant", "seed", "return target",
            *[f"cost @ {c:g}" for c in COST_TARGETS], "Spearman", "cost per doubling (95%)",
            "data median", "< max(median, 20) @ 20", "pass"]
    rows = []
    for res in results:
        for r in res["rows"]:
            rho = "n/a" if r["spearman"] is None else f"{r['spearman']:.2f}"
            rows.append([res["task"], res.get("variant", "cpu"), res["seed"],
                         return_label(r),
                         *[f"{c:.1f}" for c in r["mean_costs"]], rho, _slope(r),
                         f"{res['data_median_cost']:.1f}", "yes" if r["below_median_at_20"]
                         else "no", "PASS" if r["passes"] else "fail"])
    lines = [markdown_table(head, rows), ""]
    for task, name in dict.fromkeys((r["task"], r.get("variant", "cpu")) for r in results):
        mine = [r for r in results if r["task"] == task and r.get("variant", "cpu") == name]
        for ratio in dict.fromkeys(row["return_ratio"] for r in mine for row in r["rows"]):
            n = sum(row["passes"] for r in mine for row in r["rows"]
                    if row["return_ratio"] == ratio)
            label = "the frontier" if ratio == "frontier" else f"{ratio:g} R_ref"
            lines.append(f"- {task}, {name}, return target {label}: {n} of {len(mine)} "
                         f"seeds pass")
    return "\n".join(lines)


def main() -> None:
    """Runs the missing (task, seed) cells, rewriting the JSON after each; prints the table."""
    from safecdt_jax.experts.collect import ACTION_RECORDINGS, EXPERT_COLLECTOR_VERSION

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default="CarGoal1,CarCircle1,PointCircle1")
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--token-bins", type=int, default=None)
    on_off = argparse.BooleanOptionalAction  # --x / --no-x; unset: the preset's value
    ap.add_argument("--token-rates", action=on_off)
    ap.add_argument("--constant-targets", action=on_off)
    ap.add_argument("--labels", choices=("episode", "policy", "auto"), default=None)
    ap.add_argument("--scale-actions", action=on_off)
    ap.add_argument("--standardize-obs", action=on_off)
    ap.add_argument("--relabel-percent", type=float, default=None,
                    help="Pareto-relabelled copies per episode (the cpu default: 1.0)")
    ap.add_argument("--c0", type=float, default=None,
                    help="trajectory weights max(0, c0 - C) (the cpu default: OSRL's 70)")
    ap.add_argument("--actions", choices=ACTION_RECORDINGS, default=DEFAULT_ACTIONS,
                    help="the source data's action recording (docs/EXPERTS.md)")
    ap.add_argument("--stochastic-actions", action=on_off,
                    default=ACTION_MODES[DEFAULT_ACTION_MODE],
                    help="act with samples of the CDT's Gaussian head (the default; --no-: "
                         "its mean, as the checkpoint says)")
    ap.add_argument("--returns", choices=("ratios", "frontier"), default="ratios",
                    help="return targets: half and all of R_ref, or each cost target's "
                         "frontier return in the data")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="any other PretrainConfig or CDTConfig field, e.g. steps=20000")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/cost_following.json"))
    args = ap.parse_args()
    variant = {k: v for k, v in (("token_bins", args.token_bins),
                                 ("token_rates", args.token_rates),
                                 ("constant_targets", args.constant_targets),
                                 ("labels", args.labels),
                                 ("scale_actions", args.scale_actions),
                                 ("standardize_obs", args.standardize_obs),
                                 ("relabel_percent", args.relabel_percent),
                                 ("c0", args.c0),
                                 ("stochastic_actions", args.stochastic_actions or None),
                                 ("returns", None if args.returns == "ratios" else args.returns),
                                 ("actions",
                                  None if args.actions == DEFAULT_ACTIONS else args.actions))
               if v is not None}
    variant.update(parse_overrides(args.set))
    name = variant_name(variant)
    old = json.loads(args.out.read_text()) if args.out.exists() else {"results": []}

    # Cells of other data (an older collector, re-trained experts) are measured again.
    tasks = args.tasks.split(",")
    current = {}
    for task in tasks:
        recorded, fingerprint = data_fingerprint(task, args.actions)
        current[task, recorded] = fingerprint

    def data_key(r: dict) -> tuple[str, str]:
        return r["task"], r.get("data", {}).get("actions") or "executed"

    # Cells without the slope are evaluated again (their cached checkpoints are reused).
    results = [r for r in old["results"] if r["episodes"] == args.episodes and same_experts(r)
               and (current[data_key(r)] == r.get("data_fingerprint") if data_key(r) in current
                    else r.get("data", {}).get("expert_collector_version")
                    == EXPERT_COLLECTOR_VERSION)
               and all("slope_per_doubling" in row for row in r["rows"])]
    done = {(r["task"], r["seed"], r.get("variant", "cpu")) for r in results}
    for task in tasks:
        for seed in (int(s) for s in args.seeds.split(",")):
            if (task, seed, name) in done:
                continue
            results.append(run_one(task, seed, args.episodes, variant))
            write_json(args.out, {"machine": machine(), "results": results,
                                  "command": " ".join(["python -m experiments.cost_following",
                                                       *sys.argv[1:]])})
            print(f"{task} {name} seed {seed}: {results[-1]['seconds']:.0f} s", flush=True)
    text = table(results)
    args.out.with_suffix(".md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
