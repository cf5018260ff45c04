"""The job behind `safecdt-jax baselines`: train every requested baseline on a pair's source
data (all seeds of an algorithm in one program), evaluate offline-only in the target task at
the budget, and write `baselines.json`, `baselines.md` (the paper's Table 7 layout, its numbers
beside ours) and `baselines_scatter.png`, each atomically. The files carry a `baselines` prefix
so that the folder of a `safecdt-jax run` (whose `results.json` supplies the Safe-CDT row) can
hold them too."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from safecdt_jax.baselines.config import ALGOS, preset
from safecdt_jax.baselines.run import (
    BC_ALGOS,
    evaluate_trained,
    load_source,
    train_baseline,
    train_bc,
)

ALL_ALGOS = ALGOS + BC_ALGOS
RESULTS_FORMAT = 1
LABELS = {"bcql": "BCQL", "bearl": "BEARL", "cpq": "CPQ", "bc_all": "BC-All",
          "bc_safe": "BC-Safe", "safe_cdt": "Safe-CDT"}

# The paper's Table 7 (B = 30, 3 seeds x 20 episodes): (reward, reward std, cost, cost std, VR %).
PAPER_TABLE7: dict[str, dict[str, tuple[float, float, float, float, float]]] = {
    "CG1-CG2": {"bearl": (7.89, 1.06, 30.75, 0.39, 95.0), "bcql": (3.93, 1.28, 24.72, 1.08, 73.3),
                "cpq": (-0.55, 0.34, 11.75, 3.49, 28.3)},
    "CC1-CC2": {"bearl": (8.29, 0.67, 31.00, 0.00, 100.0),
                "bcql": (5.35, 0.42, 31.00, 0.00, 100.0), "cpq": (-0.07, 0.43, 1.37, 0.75, 0.0)},
    "PC1-PC2": {"bearl": (12.81, 2.05, 26.97, 5.24, 83.3),
                "bcql": (16.89, 3.11, 17.22, 7.93, 51.7), "cpq": (-1.05, 2.69, 20.98, 17.49, 71.7)},
}

# The paper's Safe-CDT rows at B = 30 (Table 4 for CG1-CG2, 15 seeds; Table 1 for the others,
# 3 seeds), shown beside a `run`'s Safe-CDT row.
PAPER_SAFE_CDT = {"CG1-CG2": (-15.93, 2.01, 8.56, 2.21, 14.4),
                  "CC1-CC2": (0.77, 0.29, 9.05, 1.60, 24.7),
                  "PC1-PC2": (-12.32, 3.30, 19.21, 3.34, 56.0)}


def parse_algos(text: str) -> list[str]:
    """'bcql,cpq' -> ['bcql', 'cpq']; ValueError names an unknown algorithm."""
    algos = [a.strip() for a in text.split(",") if a.strip()]
    bad = [a for a in algos if a not in ALL_ALGOS]
    if bad or not algos:
        raise ValueError(f"unknown baseline {', '.join(bad) or '(none)'}; choose from "
                         f"{', '.join(ALL_ALGOS)}")
    return algos


def summarize(returns: np.ndarray, costs: np.ndarray, budget: float) -> dict[str, float]:
    """Mean and population std over seeds of the per-seed mean return, mean cost and VR (% of
    episodes costing more than `budget`), from [seeds, episodes] arrays."""
    from safecdt_jax.results.tables import summarize_runs

    return summarize_runs({"return": returns, "cost": costs, "violation": costs > budget})


def run_baselines(pair: str, algos: Sequence[str], seeds: int, budget: float = 30.0,
                  preset_name: str = "cpu", episodes: int = 20, out: str | os.PathLike = ".",
                  data_path: str | os.PathLike | None = None, steps: int | None = None,
                  stop_over_budget: bool = True, overwrite: bool = False,
                  progress: bool = True, ckpt_dir: str | os.PathLike | None = None
                  ) -> dict[str, Any]:
    """Trains `algos` (seeds 0..seeds-1) on `pair`'s source data (the cached default, collected
    if missing, unless `data_path`), evaluates each seed for `episodes` episodes in the target
    task under the runtime budget (`stop_over_budget`), writes the results into `out` and
    returns them. `steps` overrides the preset's updates (Q-learning) or BC's steps.
    Checkpoints go to `ckpt_dir/<algo>` (default `out/ckpt`) and are reused when config, data
    and seeds match."""
    from safecdt_jax.envs import env_version
    from safecdt_jax.experts.collect import ensure_source_data
    from safecdt_jax.pairs import parse_pair
    from safecdt_jax.pretrain.run import dataset_record
    from safecdt_jax.versions import versions

    source, target = parse_pair(pair)
    if not (isinstance(seeds, int) and seeds >= 1):
        raise ValueError(f"seeds must be a positive integer, got {seeds!r}")
    if not (isinstance(episodes, int) and episodes >= 1):
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if not budget > 0:
        raise ValueError(f"the cost budget must be positive, got {budget!r}")
    out = Path(out).expanduser()
    ckpt_dir = out / "ckpt" if ckpt_dir is None else Path(ckpt_dir).expanduser()
    path = Path(data_path) if data_path is not None else ensure_source_data(source)
    data = load_source(path, source)
    stop = budget if stop_over_budget else None
    record = dataset_record(path, data)  # its fingerprint also keys the checkpoints
    methods = []
    for algo in parse_algos(",".join(algos)):
        if algo in BC_ALGOS:
            trained = train_bc(algo, data, range(seeds), budget, steps, progress)
        else:
            cfg = preset(algo, preset_name, cost_limit=float(budget),
                         **({} if steps is None else {"steps": steps}))
            trained = train_baseline(cfg, data, range(seeds), ckpt_dir / algo,
                                     overwrite=overwrite, progress=progress,
                                     data_id=record["fingerprint"])
        start = time.perf_counter()
        returns, costs = evaluate_trained(trained, target, episodes, seed=1, stop_cost=stop)
        methods.append({
            "algo": algo, "config": trained.config, "train_seconds": trained.seconds,
            "eval_seconds": time.perf_counter() - start, "reused": trained.reused,
            "history": {k: np.asarray(v).tolist() for k, v in trained.history.items()},
            "returns": returns.tolist(), "costs": costs.tolist(),
            "summary": summarize(returns, costs, budget)})
        if progress:
            s = methods[-1]["summary"]
            print(f"{LABELS[algo]}: reward {s['mean_return_mean']:.2f}, cost "
                  f"{s['mean_cost_mean']:.2f}, VR {s['vr_mean']:.1f}%", flush=True)
    results = {"format": RESULTS_FORMAT, "pair": pair, "source": source, "target": target,
               "target_env": env_version(target), "budget": budget, "seeds": seeds,
               "episodes": episodes, "preset": preset_name, "stop_over_budget": stop_over_budget,
               "data": record, "versions": versions(),
               "created": time.strftime("%Y-%m-%d %H:%M:%S"), "methods": methods}
    write_baselines(out, results)
    return results


def safe_cdt_row(folder: Path, budget: float) -> dict[str, Any] | None:
    """The `safe_cdt` run at `budget` of a deployment `results.json` in `folder`, as a method
    entry (label, summary, per-seed means), or None when there is none."""
    path = folder / "results.json"
    if not path.is_file():
        return None
    runs = json.loads(path.read_text()).get("runs", [])
    for run in runs:
        if run.get("variant") == "safe_cdt" and float(run.get("budget", -1)) == budget \
                and not run.get("dynamics"):
            return {"algo": "safe_cdt", "summary": run["summary"],
                    "returns": run["metrics"]["return"], "costs": run["metrics"]["cost"]}
    return None


def _cell(mean: float, std: float) -> str:
    return f"{mean:.2f} ± {std:.2f}"


def baselines_table(results: dict[str, Any], extra: Sequence[dict] = ()) -> str:
    """The paper's Table 7 rows for our runs, with the paper's reward, cost and VR beside (for a
    Safe-CDT row from a `run`, the paper's Table 4 / Table 1 row)."""
    from safecdt_jax.results.tables import markdown_table

    paper = PAPER_TABLE7.get(results["pair"], {}) | (
        {"safe_cdt": PAPER_SAFE_CDT[results["pair"]]} if results["pair"] in PAPER_SAFE_CDT
        else {})
    rows = []
    for m in list(results["methods"]) + list(extra):
        s = m["summary"]
        p = paper.get(m["algo"])
        ours = [_cell(s["mean_return_mean"], s["mean_return_std"]),
                _cell(s["mean_cost_mean"], s["mean_cost_std"]), f"{s['vr_mean']:.1f}"]
        theirs = ["-"] * 3 if p is None else [_cell(p[0], p[1]), _cell(p[2], p[3]), f"{p[4]:.1f}"]
        rows.append([results["pair"].replace("-", "→"), LABELS[m["algo"]], *ours, *theirs])
    return markdown_table(["Pair", "Method", "Reward", "Cost", "VR (%)", "paper reward",
                           "paper cost", "paper VR (%)"], rows)


def plot_scatter(methods: Sequence[dict], budget: float, title: str,
                 path: str | os.PathLike) -> Path:
    """Mean episode cost (x) against mean return (y), one point per (method, seed), the budget
    drawn; written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from safecdt_jax.results.figures import save_png

    fig, ax = plt.subplots(figsize=(5.5, 4))
    for m in methods:
        cost = np.asarray(m["costs"], np.float64).mean(-1)
        ret = np.asarray(m["returns"], np.float64).mean(-1)
        ax.scatter(cost, ret, label=m.get("label") or LABELS[m["algo"]], alpha=0.8)
    ax.axvline(budget, color="k", ls="--", lw=1, label=f"budget {budget:g}")
    ax.set_xlabel("mean episode cost (per seed)")
    ax.set_ylabel("mean episode return (per seed)")
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_png(fig, path)


def write_baselines(out: str | os.PathLike, results: dict[str, Any]) -> list[Path]:
    """Writes `baselines.json`, `baselines.md` and `baselines_scatter.png` into `out`."""
    from safecdt_jax.io import write_text_atomic

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    extra = [r for r in [safe_cdt_row(out, results["budget"])] if r is not None]
    times = ", ".join(f"{LABELS[m['algo']]} {m['train_seconds']:.0f} s"
                      + (" (reused)" if m["reused"] else "") for m in results["methods"])
    protocol = ("each episode ended at the first step over the budget (the paper's runtime "
                "budget)" if results["stop_over_budget"] else "full episodes")
    header = (f"# Offline baselines, {results['pair']}\n\n{results['source']} data -> "
              f"{results['target']}, budget {results['budget']:g}, {results['seeds']} seeds x "
              f"{results['episodes']} episodes, `{results['preset']}` preset; {protocol}. "
              f"Reward, cost, VR: mean ± population std over seeds. Training: {times}. "
              f"Made {results['created']}.\n\n")
    return [
        write_text_atomic(out / "baselines.json", json.dumps(results, indent=1)),
        write_text_atomic(out / "baselines.md", header + baselines_table(results, extra) + "\n"),
        plot_scatter(list(results["methods"]) + extra, results["budget"],
                     f"{results['pair']}, B={results['budget']:g}",
                     out / "baselines_scatter.png"),
    ]


__all__ = ["ALL_ALGOS", "PAPER_SAFE_CDT", "PAPER_TABLE7", "baselines_table", "parse_algos",
           "plot_scatter", "run_baselines", "safe_cdt_row", "summarize", "write_baselines"]
