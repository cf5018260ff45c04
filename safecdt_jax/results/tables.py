"""Per-seed summaries and the paper's table rows (reward, cost, VR as mean +- std over seeds)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

# Per-episode metric arrays of a deployment, each [seeds, episodes] (docs/METHOD.md section 6).
METRIC_NAMES = ("return", "cost", "violation", "ctg_target", "rtg_target", "lambda", "a_c", "a_r",
                "lora_loss")


def seed_summaries(metrics: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Per-seed VR (% of episodes whose cost exceeded the budget), mean return, mean cost.

    `metrics` holds `return`, `cost`, `violation` arrays [seeds, episodes]; returns three [seeds]
    arrays `vr`, `mean_return`, `mean_cost`.
    """
    return {
        "vr": 100.0 * np.asarray(metrics["violation"], np.float64).mean(axis=-1),
        "mean_return": np.asarray(metrics["return"], np.float64).mean(axis=-1),
        "mean_cost": np.asarray(metrics["cost"], np.float64).mean(axis=-1),
    }


def summarize_runs(metrics: Mapping[str, Any], checkpoints: int = 1) -> dict[str, float]:
    """Across seeds: mean and std (population std, numpy's default) of each per-seed summary.

    With `checkpoints` > 1 the seeds are checkpoint-major (`checkpoints` pretrained models,
    each deployed with the same deployment seeds) and each summary also gets its two spreads:
    `_between_std`, the std of the checkpoints' means, and `_within_std`, the mean over
    checkpoints of the std across deployment seeds."""
    out: dict[str, float] = {}
    for name, values in seed_summaries(metrics).items():
        out[f"{name}_mean"] = float(values.mean())
        out[f"{name}_std"] = float(values.std())
        if checkpoints > 1:
            grid = np.asarray(values).reshape(checkpoints, -1)
            out[f"{name}_between_std"] = float(grid.mean(1).std())
            out[f"{name}_within_std"] = float(grid.std(1).mean())
    out["seeds"] = int(np.shape(metrics["cost"])[0])
    if checkpoints > 1:
        out["checkpoints"] = checkpoints
    return out


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub markdown table: one header row, then one row per entry (cells via `str`)."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def results_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The paper's Table 1 layout: one row per run with Reward, Cost, VR (%) as mean +- std.

    Each row needs `label` and the keys of `summarize_runs`.
    """
    cells = [[r["label"], f"{r['mean_return_mean']:.2f}±{r['mean_return_std']:.2f}",
              f"{r['mean_cost_mean']:.2f}±{r['mean_cost_std']:.2f}",
              f"{r['vr_mean']:.1f}±{r['vr_std']:.1f}", r["seeds"]] for r in rows]
    return markdown_table(["run", "Reward", "Cost", "VR (%)", "seeds"], cells) + "\n"
