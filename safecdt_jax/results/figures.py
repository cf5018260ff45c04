"""Deployment figures: cost, CTG target and violation rate per scheduler stage; robustness."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from safecdt_jax.io import atomic_path


def save_png(fig, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Write a pyplot figure to `path` as PNG atomically (`io.atomic_path`) and close
    it; returns the path."""
    import matplotlib.pyplot as plt

    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    plt.close(fig)
    return Path(path)


def stage_means(values, stage_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-stage summary of a [seeds, episodes] metric: (stage index from 1, mean over seeds of
    each seed's stage mean, half-width of its 95% interval, 1.96 standard errors over seeds;
    0 for one seed). A last partial stage is averaged over the episodes it has."""
    values = np.asarray(values, np.float64)
    seeds, episodes = values.shape
    stages = -(-episodes // stage_len)
    per_seed = np.stack([values[:, k * stage_len:(k + 1) * stage_len].mean(axis=1)
                         for k in range(stages)], axis=1)
    half = (1.96 * per_seed.std(axis=0, ddof=1) / np.sqrt(seeds) if seeds > 1
            else np.zeros(stages))
    return np.arange(1, stages + 1), per_seed.mean(axis=0), half


def plot_deployment(
    runs: Mapping[str, Mapping[str, Any]], budget: float, out_dir: str | os.PathLike, title: str,
    stage_len: int = 5,
) -> list[str]:
    """Write `cost.png`, `ctg_target.png` and `violation_rate.png` into `out_dir`.

    `runs` maps a run label (e.g. a variant) to its metrics, arrays [seeds, episodes]: `cost`
    (episode cost, cost units), `ctg_target` (raw cost-to-go target), `violation` (0/1). Each
    figure shows, per scheduler stage of `stage_len` episodes, the mean over seeds of each
    seed's stage mean with its 95% interval (`stage_means`): one episode is too noisy to read
    (a cut episode costs B + 1, the next one may cost 0). Returns the written paths; each file
    is written atomically (`io.atomic_path`).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    os.makedirs(out_dir, exist_ok=True)
    specs = [
        ("cost.png", "cost", "episode cost", 1.0),
        ("ctg_target.png", "ctg_target", "cost-to-go target", 1.0),
        ("violation_rate.png", "violation", "violation rate (%)", 100.0),
    ]
    paths = []
    for filename, key, ylabel, scale in specs:
        fig, ax = plt.subplots(figsize=(6.4, 3.6))
        for label, metrics in runs.items():
            stage, mean, half = stage_means(scale * np.asarray(metrics[key], np.float64),
                                            stage_len)
            line, = ax.plot(stage, mean, marker="o", ms=3, label=label)
            ax.fill_between(stage, mean - half, mean + half, alpha=0.2, color=line.get_color())
        if key != "violation":
            ax.axhline(budget, color="k", ls="--", lw=1, label=f"budget {budget:g}")
        ax.set_xlabel(f"stage ({stage_len} episodes each)")
        ax.set_ylabel(f"{ylabel}, stage mean (95% CI over seeds)")
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
