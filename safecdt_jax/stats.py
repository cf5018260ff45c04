"""Small statistics of episodes, seeds and checkpoints, shared by the experiments in `experiments/`.

    ratio_interval(theirs, ours)          # bootstrap interval of mean(theirs) / mean(ours)
    doubling_slope(targets, costs)        # cost per doubling of the cost target, with its interval
    frontier_returns(returns, costs, targets)   # the data's return at each cost target
    per_seed_metrics(run)                 # VR, cost, late cost, drift, reward of each seed
    seed_spread(values)                   # mean, spread across checkpoints and across seeds

All take and return plain numbers or NumPy arrays (float64); nothing here runs JAX.
"""

from __future__ import annotations

import numpy as np


def ratio_interval(theirs: np.ndarray, ours: np.ndarray, level: float = 0.95,
                   resamples: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of mean(theirs) / mean(ours) (unitless), each sample
    resampled with replacement on its own (the two simulators' episodes are independent).
    A resampled denominator of 0 gives an infinite ratio, so an interval can end at inf."""
    theirs, ours = np.asarray(theirs, np.float64), np.asarray(ours, np.float64)
    if theirs.size == 0 or ours.size == 0:
        raise ValueError("ratio_interval needs at least one episode on each side")
    rng = np.random.default_rng(seed)
    num = theirs[rng.integers(0, theirs.size, (resamples, theirs.size))].mean(1)
    den = ours[rng.integers(0, ours.size, (resamples, ours.size))].mean(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)
    lo, hi = np.quantile(ratio, [(1 - level) / 2, (1 + level) / 2], method="inverted_cdf")
    return float(lo), float(hi)


def doubling_slope(targets, costs, draws: int = 2000, seed: int = 0) -> dict:
    """How much the episode cost rises per doubling of the cost target, with a 95% interval.

    `targets` [n] cost targets, `costs` [n, episodes] episode costs at each. The slope is the
    least-squares fit of episode cost on log2(target) (cost steps per doubling); the interval
    is the 2.5-97.5 percentile of the slopes of `draws` bootstrap resamples of the episodes,
    drawn within each target. A model whose cost ignores its target has an interval around 0,
    however its four means happen to order (a Spearman >= 0.8 among four exchangeable means
    has probability 1/6). Returns `{"slope", "low", "high"}`.
    """
    x = np.log2(np.asarray(targets, np.float64))
    y = np.asarray(costs, np.float64)
    if y.ndim != 2 or y.shape[0] != x.size or x.size < 2 or np.ptp(x) == 0:
        raise ValueError(f"doubling_slope needs >= 2 distinct targets and costs [targets, "
                         f"episodes], got {x.size} targets and costs of shape {y.shape}")
    xc = x - x.mean()

    def fit(means):  # equal episodes per target: the OLS slope through the per-target means
        return float(xc @ (means - means.mean()) / (xc @ xc))

    rng = np.random.default_rng(seed)
    pick = rng.integers(0, y.shape[1], size=(draws, *y.shape))
    boot = np.take_along_axis(y[None], pick, axis=2).mean(axis=2)  # [draws, targets]
    slopes = (boot - boot.mean(axis=1, keepdims=True)) @ xc / (xc @ xc)
    low, high = np.percentile(slopes, [2.5, 97.5])
    return {"slope": fit(y.mean(axis=1)), "low": float(low), "high": float(high)}


def frontier_returns(returns, costs, targets, q: float = 90.0) -> list[float]:
    """The data's return frontier at each cost target: for target c, the `q`-th percentile of
    the episode returns of the episodes whose cost is at most c (a high quantile rather than
    the best episode, which on a wide data set is one lucky layout).

    `returns`, `costs`: per-episode sums (reward and cost steps). Raises ValueError when a
    target has no episode at or below it, where no return is feasible."""
    returns, costs = np.asarray(returns, np.float64), np.asarray(costs, np.float64)
    if returns.shape != costs.shape or returns.ndim != 1:
        raise ValueError(f"frontier_returns needs per-episode returns and costs of one shape, "
                         f"got {returns.shape} and {costs.shape}")
    out = []
    for c in targets:
        under = returns[costs <= c]
        if under.size == 0:
            raise ValueError(f"frontier_returns: no episode of the data costs at most {c:g}")
        out.append(float(np.percentile(under, q)))
    return out


def per_seed_metrics(run: dict) -> dict[str, np.ndarray]:
    """[seeds] arrays of one run of a deployment's results.json (`run["metrics"]` holds
    [seeds, episodes] `cost`, `violation`, `return`): VR (%), mean cost, mean cost of the last
    10 episodes (`late`), the drift (last 10 minus first 10 episodes' mean cost), mean return."""
    cost = np.asarray(run["metrics"]["cost"])
    return {"vr": 100 * np.asarray(run["metrics"]["violation"], float).mean(1),
            "cost": cost.mean(1), "late": cost[:, -10:].mean(1),
            "drift": cost[:, -10:].mean(1) - cost[:, :10].mean(1),
            "reward": np.asarray(run["metrics"]["return"]).mean(1)}


def seed_spread(values: list[np.ndarray]) -> dict[str, float]:
    """`values`: one [seeds] array per checkpoint. The mean over checkpoints x seeds, the std of
    the checkpoints' means (`ckpt_std`) and the mean of their seed stds (`seed_std`)."""
    v = np.asarray(values)
    return {"mean": float(v.mean()), "ckpt_std": float(v.mean(1).std()),
            "seed_std": float(v.std(1).mean())}
