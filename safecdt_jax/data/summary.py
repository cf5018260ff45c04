"""Per-episode return/cost figures of a data set, and its reward-cost scatter plot."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from safecdt_jax.data.dataset import Dataset
from safecdt_jax.data.dsrl import load_dataset
from safecdt_jax.data.windows import episode_costs, episode_returns
from safecdt_jax.io import atomic_path


def _num(x) -> float | None:
    return None if x is None else float(x)


def _tag(x: float) -> str:
    return f"{x:g}".replace(".", "p").replace("-", "m")


def summarize_dataset(
    path_or_dataset: str | os.PathLike | Dataset,
    png_path: str | os.PathLike | None = None,
    *,
    budget: float = 30.0,
    safe_cost: float = 10.0,
    high_cost: float = 100.0,
) -> dict[str, Any]:
    """Episode statistics in raw units (undiscounted, unscaled sums of the logged rewards/costs).

    Relabelling offsets are ignored: these are the realised episodes. Keys (defaults shown):
    n_episodes, n_transitions; return_min/max/median/mean; cost_min/max/median/mean;
    frac_cost_le_30 and frac_cost_gt_30 (fractions of episodes with cost <= / > `budget`);
    best_return_cost_le_10 (best return among cost <= `safe_cost`) and best_return_cost_30_100
    (among `budget` < cost <= `high_cost`), None when no episode qualifies; n_cost_le_10 and
    n_cost_30_100 (how many qualify). Key names follow the thresholds (30.5 -> "30p5").
    cost_share_by_snapshot and return_share_by_snapshot: for expert data (episode_info
    "snapshot"), the fraction of the episodes' cost (return) variance that lies between the
    snapshots' means (1: the policy decides the cost; near 0: the layout and the sampling do);
    None without snapshot ids or with a constant quantity.
    policy_cost_min / policy_cost_max: the lowest and highest mean episode cost of a behaviour
    policy (episodes sharing a snapshot id), and policy_cost_shares: the share of episodes
    whose policy's mean cost falls in each of `POLICY_COST_BANDS` ({'<=5': 0.12, ...}); all
    None without snapshot ids.
    With `png_path`, writes a reward-cost scatter PNG there atomically (matplotlib Agg).
    JSON-serialisable: plain Python numbers and None.
    """
    data = path_or_dataset
    if not isinstance(data, Dataset):
        data = load_dataset(data)
    lengths = np.asarray(data.lengths)
    returns, costs = episode_returns(data), episode_costs(data)  # float64 sums over valid steps
    if returns.size == 0:
        raise ValueError("summarize_dataset: the data set has no episodes")

    safe = costs <= safe_cost
    mid = (costs > budget) & (costs <= high_cost)
    b, s, h = _tag(budget), _tag(safe_cost), _tag(high_cost)
    out: dict[str, Any] = {
        "n_episodes": int(returns.size),
        "n_transitions": int(lengths.sum()),
        "return_min": float(returns.min()),
        "return_max": float(returns.max()),
        "return_median": float(np.median(returns)),
        "return_mean": float(returns.mean()),
        "cost_min": float(costs.min()),
        "cost_max": float(costs.max()),
        "cost_median": float(np.median(costs)),
        "cost_mean": float(costs.mean()),
        f"frac_cost_le_{b}": float(np.mean(costs <= budget)),
        f"frac_cost_gt_{b}": float(np.mean(costs > budget)),
        f"best_return_cost_le_{s}": _num(returns[safe].max() if safe.any() else None),
        f"best_return_cost_{b}_{h}": _num(returns[mid].max() if mid.any() else None),
        f"n_cost_le_{s}": int(safe.sum()),
        f"n_cost_{b}_{h}": int(mid.sum()),
    }
    groups = data.episode_info.get("snapshot")
    out["cost_share_by_snapshot"] = between_group_share(costs, groups)
    out["return_share_by_snapshot"] = between_group_share(returns, groups)
    out |= policy_cost_bands(costs, groups, data.episode_info.get("policy_cost"))
    if png_path is not None:
        _scatter(png_path, costs, returns, budget, str(data.attrs.get("task", "")))
    return out


# Bands of a behaviour policy's mean episode cost (raw units), upper edges inclusive: careful
# (<= 5, the careful-data issue's level), moderate, around a budget of 30, and reckless.
POLICY_COST_BANDS = ((0.0, 5.0), (5.0, 20.0), (20.0, 60.0), (60.0, float("inf")))


def _band_name(lo: float, hi: float) -> str:
    return f"<={hi:g}" if lo == 0 else (f">{lo:g}" if hi == float("inf") else f"{lo:g}-{hi:g}")


def policy_cost_bands(costs: np.ndarray, groups: np.ndarray | None,
                      recorded: np.ndarray | None = None) -> dict[str, Any]:
    """The range of the per-policy mean episode costs (raw units) and the share of episodes
    per band of their policy's mean (`POLICY_COST_BANDS`; a mean of exactly 5 is '<=5').
    The means are `recorded` (per episode, its policy's mean over all its rollouts, as the
    expert collector stores it) when given, else the means over the episodes here.
    Keys policy_cost_min, policy_cost_max, policy_cost_shares; None each without groups."""
    if groups is None:
        return {"policy_cost_min": None, "policy_cost_max": None, "policy_cost_shares": None}
    _, idx, counts = np.unique(np.asarray(groups), return_inverse=True, return_counts=True)
    idx = idx.reshape(-1)
    means = np.bincount(idx, weights=np.asarray(costs, np.float64)) / counts
    if recorded is not None:  # every episode of a policy carries the same recorded mean
        recorded = np.asarray(recorded, np.float64).reshape(-1)
        means = np.bincount(idx, weights=recorded) / counts
    per_episode = means[idx]
    shares = {_band_name(lo, hi): float(np.mean((per_episode > lo) & (per_episode <= hi))
                                        if lo > 0 else np.mean(per_episode <= hi))
              for lo, hi in POLICY_COST_BANDS}
    return {"policy_cost_min": float(means.min()), "policy_cost_max": float(means.max()),
            "policy_cost_shares": shares}


def between_group_share(values: np.ndarray, groups: np.ndarray | None) -> float | None:
    """Fraction of the (population) variance of `values` that lies between the group means:
    sum_g n_g (mean_g - mean)^2 / sum_i (v_i - mean)^2, in [0, 1]. None when `groups` is None
    or the values are constant."""
    if groups is None:
        return None
    values = np.asarray(values, np.float64)
    total = np.sum((values - values.mean()) ** 2)
    if total == 0:
        return None
    _, idx, counts = np.unique(np.asarray(groups), return_inverse=True, return_counts=True)
    means = np.bincount(idx, weights=values) / counts
    return float(np.sum(counts * (means - values.mean()) ** 2) / total)


def _scatter(png_path, costs, returns, budget: float, title: str) -> None:
    """Reward-cost scatter with the budget line; the figure object avoids pyplot's global state."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.scatter(costs, returns, s=6, alpha=0.6)
    ax.axvline(budget, color="tab:red", linestyle="--", linewidth=1, label=f"cost = {budget:g}")
    ax.set_xlabel("episode cost")
    ax.set_ylabel("episode return")
    ax.set_title(title or f"{costs.size} episodes")
    ax.legend(loc="best")
    fig.tight_layout()
    with atomic_path(png_path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
