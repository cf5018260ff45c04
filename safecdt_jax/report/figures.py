"""Deployment figures: per-episode cost across seeds, the CTG target trace, violation rate."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from safecdt_jax.data.dataset import atomic_path


def save_png(fig, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Write a pyplot figure to `path` as PNG atomically (`data.dataset.atomic_path`) and close
    it; returns the path."""
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    plt.close(fig)
    return Path(path)


def _band(ax, values: np.ndarray, label: str, color=None) -> None:
    """Median across seeds with the 25-75% band, against the 1-based episode index."""
    episodes = np.arange(1, values.shape[1] + 1)
    lo, mid, hi = np.percentile(values, [25, 50, 75], axis=0)
    line, = ax.plot(episodes, mid, label=label, color=color)
    ax.fill_between(episodes, lo, hi, alpha=0.2, color=line.get_color())


def plot_deployment(
    runs: Mapping[str, Mapping[str, Any]], budget: float, out_dir: str | os.PathLike, title: str
) -> list[str]:
    """Write `cost.png`, `ctg_target.png` and `violation_rate.png` into `out_dir`.

    `runs` maps a run label (e.g. a variant) to its metrics, arrays [seeds, episodes]: `cost`
    (episode cost, cost steps), `ctg_target` (raw cost-to-go target), `violation` (0/1).
    Returns the written paths. Each file is written atomically (`data.dataset.atomic_path`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    specs = [
        ("cost.png", "cost", "episode cost (median, 25-75% over seeds)", True),
        ("ctg_target.png", "ctg_target", "cost-to-go target", True),
        ("violation_rate.png", "violation", "violation rate across seeds (%)", False),
    ]
    paths = []
    for filename, key, ylabel, band in specs:
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        for label, metrics in runs.items():
            values = np.asarray(metrics[key], np.float64)
            if band:
                _band(ax, values, label)
            else:
                ax.plot(np.arange(1, values.shape[1] + 1), 100 * values.mean(axis=0), label=label)
        if key != "violation":
            ax.axhline(budget, color="k", ls="--", lw=1, label=f"budget {budget:g}")
        ax.set_xlabel("episode")
        ax.set_ylabel(ylabel)
        ax.set_title(title)
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(os.fspath(save_png(fig, os.path.join(out_dir, filename))))
    return paths


def plot_robustness(runs: list[Mapping[str, Any]], field: str, out_path: str | os.PathLike,
                    title: str) -> str:
    """Write a two-panel PNG: mean episode cost and VR (%) against the shift value `field`,
    one line per group of runs that differ only in that value, mean +- std over seeds, each
    line's budget drawn on the cost panel.

    Each run needs `variant`, `budget`, `dynamics` ({field: scale}) and `summary`
    (`summarize_runs`). Written atomically; returns the path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[str, list] = {}
    for run in runs:
        rest = {k: v for k, v in run["dynamics"].items() if k != field}
        label = run["variant"] + "".join(f" {k}={v:g}" for k, v in rest.items())
        label += f" B={run['budget']:g}" if len({r["budget"] for r in runs}) > 1 else ""
        groups.setdefault(label, []).append(run)
    fig, (ax_c, ax_v) = plt.subplots(1, 2, figsize=(9.6, 3.6))
    for label, members in groups.items():
        members = sorted(members, key=lambda r: r["dynamics"][field])
        x = [r["dynamics"][field] for r in members]
        s = [r["summary"] for r in members]
        line = ax_c.errorbar(x, [v["mean_cost_mean"] for v in s],
                             yerr=[v["mean_cost_std"] for v in s], marker="o", capsize=3,
                             label=label)
        ax_c.axhline(members[0]["budget"], color=line[0].get_color(), ls="--", lw=1)
        ax_v.errorbar(x, [v["vr_mean"] for v in s], yerr=[v["vr_std"] for v in s], marker="o",
                      capsize=3, label=label)
    ax_c.set_ylabel("mean episode cost (dashed: budget)")
    ax_v.set_ylabel("violation rate VR (%)")
    for ax in (ax_c, ax_v):
        ax.set_xlabel(field)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return os.fspath(save_png(fig, out_path))
