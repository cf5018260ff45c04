"""OSRL's Pareto-frontier return relabelling ("augmentation", docs/METHOD.md A.3), in numpy.

A preprocessing step run once before training: it appends relabelled copies of real episodes whose
whole return-to-go and cost-to-go sequences are shifted by per-episode constants (via
`return_offset` / `cost_offset`); observations, actions, rewards and costs are copied unchanged.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.data.dataset import Dataset, select_episodes
from safecdt_jax.data.windows import episode_costs, episode_returns


@dataclasses.dataclass(frozen=True)
class RelabelConfig:
    """Settings of the Pareto relabelling; defaults are OSRL's CDT defaults.

    enabled: False makes `relabel_pareto` return its input unchanged.
    percent: relabelled copies = int(percent * |F|), F the grid-filtered episodes (OSRL 0.2).
    cost_bins, reward_bins: grid over the data's (cost, return) range (10 x 50).
    max_per_bin: a fuller bin is randomly subsampled to this many episodes (10).
    min_per_bin: a bin with fewer episodes is dropped (3, i.e. OSRL drops bins with <= 2).
    deg: degree of the polynomial fitted to the Pareto front (OSRL: per task 0-4; Goal and Circle
      tasks mostly 1). Lowered to (number of distinct front costs - 1) when the front is smaller.
    min_reward: targets start this far above the fitted front (raw return units, 1).
    max_reward: upper end of the target returns (raw units; OSRL sets it per task, e.g. 50 for
      CarGoal1). None: the best episode return plus 20% of the data's return range.
    max_rew_decrease: a re-drawn duplicate may lose at most this much return (raw units, 5).
    beta: re-draw probabilities are 1 / (distance + beta) (1).
    """

    enabled: bool = True
    percent: float = 0.2
    cost_bins: int = 10
    reward_bins: int = 50
    max_per_bin: int = 10
    min_per_bin: int = 3
    deg: int = 1
    min_reward: float = 1.0
    max_reward: float | None = None
    max_rew_decrease: float = 5.0
    beta: float = 1.0


def as_rng(key_or_rng) -> np.random.Generator:
    """A numpy Generator from a JAX PRNG key (raw or typed), a Generator, or an int seed."""
    if isinstance(key_or_rng, np.random.Generator):
        return key_or_rng
    if isinstance(key_or_rng, int | np.integer):
        return np.random.default_rng(int(key_or_rng))
    bits = jax.random.bits(key_or_rng, (4,), jnp.uint32)
    return np.random.default_rng(np.asarray(bits, np.uint64))


def _bin(x: np.ndarray, bins: int) -> np.ndarray:
    lo, hi = x.min(), x.max()
    if hi <= lo:
        return np.zeros(x.shape, np.int64)
    return np.clip(((x - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1)


def grid_filter(
    rng: np.random.Generator, costs, returns, cfg: RelabelConfig = RelabelConfig()
) -> np.ndarray:
    """Indices (sorted) kept by the outlier grid: at most `max_per_bin` per (cost, return) bin,
    bins holding fewer than `min_per_bin` episodes dropped. Bins span the data's range."""
    costs, returns = np.asarray(costs, np.float64), np.asarray(returns, np.float64)
    cell = _bin(costs, cfg.cost_bins) * cfg.reward_bins + _bin(returns, cfg.reward_bins)
    kept = []
    for c in np.unique(cell):
        members = np.flatnonzero(cell == c)
        if members.size < cfg.min_per_bin:
            continue
        if members.size > cfg.max_per_bin:
            members = rng.choice(members, cfg.max_per_bin, replace=False)
        kept.append(members)
    return np.sort(np.concatenate(kept)) if kept else np.zeros(0, np.int64)


def pareto_front(costs, returns) -> np.ndarray:
    """Indices of the non-dominated points (minimise cost, maximise return).

    j dominates i when C_j <= C_i and R_j >= R_i with one inequality strict; exact duplicates do
    not dominate each other, so all copies of a front point are kept.
    """
    c, r = np.asarray(costs, np.float64), np.asarray(returns, np.float64)
    no_worse = (c[:, None] <= c[None, :]) & (r[:, None] >= r[None, :])
    better = (c[:, None] < c[None, :]) | (r[:, None] > r[None, :])
    return np.flatnonzero(~np.any(no_worse & better, axis=0))


def _associate(rng, c_f, r_f, targets, cfg: RelabelConfig) -> np.ndarray:
    """For each (c, r) target, the index into F of the episode whose returns it relabels.

    Nearest F-episode in raw Euclidean (C, R) distance among those with C_j <= c. When an episode
    is nearest for k > 1 targets, its first target keeps it; each later one gets a re-draw among
    F-episodes with C_j <= C_i and R_j >= R_i - max_rew_decrease (i itself included), with
    probability proportional to 1 / (distance to episode i + beta). Unlike OSRL, the re-draws stay
    paired with their own targets in target order (OSRL regroups them, pairing only roughly).
    """
    dist = np.hypot(targets[:, :1] - c_f[None, :], targets[:, 1:] - r_f[None, :])
    dist = np.where(c_f[None, :] <= targets[:, :1], dist, np.inf)
    chosen = np.argmin(dist, axis=1)
    seen: set[int] = set()
    for t, i in enumerate(chosen.tolist()):
        if i not in seen:
            seen.add(i)
            continue
        ok = (c_f <= c_f[i]) & (r_f >= r_f[i] - cfg.max_rew_decrease)
        cand = np.flatnonzero(ok)
        w = 1.0 / (np.hypot(c_f[cand] - c_f[i], r_f[cand] - r_f[i]) + cfg.beta)
        chosen[t] = cand[rng.choice(cand.size, p=w / w.sum())]
    return chosen


def relabel_pareto(key_or_rng, data: Dataset, cfg: RelabelConfig = RelabelConfig()) -> Dataset:
    """Append Pareto-relabelled copies of episodes (OSRL CDT augmentation, docs/METHOD.md A.3).

    1. Per-episode (C_i, R_i) = cost-/return-to-go at t=0, raw units. 2. Grid-filter to F
    (`grid_filter`). 3. Fit a degree-`deg` polynomial f to the Pareto front of F. 4. n =
    int(percent*|F|) targets: costs linspace(min C_F, max C_F, n), returns uniform in
    [f(c) + min_reward, max_reward] (just f(c) + min_reward where that exceeds max_reward).
    5. Pair each target with an episode (`_associate`). 6. Each copy gets constant offsets so its
    RTG at t=0 is the target return and its CTG at t=0 the target cost (cost shift >= 0).
    Returns all original episodes followed by the n copies; `episode_info["relabel_source"]` is
    the source episode index for copies and -1 for originals. Only offsets differ from the source.
    With `enabled=False` or n = 0 the data come back unchanged. `key_or_rng`: see `as_rng`.
    """
    if not cfg.enabled:
        return data
    rng = as_rng(key_or_rng)
    costs, returns = episode_costs(data), episode_returns(data)
    real = np.flatnonzero(np.asarray(data.lengths) > 0)
    filtered = real[grid_filter(rng, costs[real], returns[real], cfg)]
    n = int(cfg.percent * filtered.size)
    if n == 0:
        return data
    c_f, r_f = costs[filtered], returns[filtered]
    front = pareto_front(c_f, r_f)
    deg = max(0, min(cfg.deg, np.unique(c_f[front]).size - 1))
    frontier = np.poly1d(np.polyfit(c_f[front], r_f[front], deg))
    if cfg.max_reward is None:
        max_reward = returns[real].max() + 0.2 * np.ptp(returns[real])
    else:
        max_reward = cfg.max_reward
    target_c = np.linspace(c_f.min(), c_f.max(), n)
    low = frontier(target_c) + cfg.min_reward
    target_r = rng.uniform(low, np.maximum(low, max_reward))
    source = filtered[_associate(rng, c_f, r_f, np.stack([target_c, target_r], 1), cfg)]

    out = select_episodes(data, np.concatenate([np.arange(data.n_episodes), source]))
    return_offset = np.asarray(out.return_offset, np.float64)
    cost_offset = np.asarray(out.cost_offset, np.float64)
    copies = slice(data.n_episodes, None)
    return_offset[copies] += target_r - returns[source]
    cost_offset[copies] += target_c - costs[source]
    info = dict(out.episode_info)
    info["relabel_source"] = np.concatenate(
        [np.full(data.n_episodes, -1, np.int64), source]
    ).astype(np.int64)
    return dataclasses.replace(
        out,
        return_offset=return_offset.astype(np.float32),
        cost_offset=cost_offset.astype(np.float32),
        episode_info=info,
    )


def policy_mean_labels(data: Dataset, key: str = "snapshot") -> Dataset:
    """Each episode's return- and cost-to-go shifted so that at t=0 they equal the mean episode
    return and cost of the policy that drove it (the episodes sharing `episode_info[key]`).

    An expert's episode cost on a Goal task is mostly the layout's luck (docs/METHOD.md,
    section 8): a label of 10 is as often a fast policy's lucky layout as a careful
    policy's normal one, so a model conditioned on realised outcomes cannot learn caution from
    it. Labelled by its policy's expectation (as ESPER does with learnt clusters; here the
    policies are known), the token names how the episode was driven. Within an episode the
    tokens still fall by the realised rewards and costs, as in deployment, so a lucky episode
    ends with budget left and an unlucky one below zero. Only `return_offset` / `cost_offset`
    change. The policy's mean is `episode_info['policy_return']` / `['policy_cost']` where the
    collector recorded it (over all the policy's rollouts, before any filter dropped some),
    else the mean over the episodes of `key` present here. Raises ValueError when
    `episode_info` has no `key`.
    """
    if key not in data.episode_info:
        raise ValueError(f"policy-mean labels need episode_info[{key!r}] (the behaviour policy "
                         f"of each episode); this data set has {sorted(data.episode_info)}")
    groups = np.unique(np.asarray(data.episode_info[key]), return_inverse=True)[1].reshape(-1)
    real = np.asarray(data.lengths) > 0
    count = np.maximum(np.bincount(groups, real.astype(np.float64)), 1.0)
    recorded = [data.episode_info.get(f"policy_{k}") if key == "snapshot" else None
                for k in ("return", "cost")]
    shifts = []
    for per_episode, known in zip((episode_returns(data), episode_costs(data)), recorded,
                                  strict=True):
        if known is not None:
            mean_of = np.asarray(known, np.float64).reshape(-1)
        else:
            mean_of = (np.bincount(groups, np.where(real, per_episode, 0.0)) / count)[groups]
        shifts.append(np.where(real, mean_of - per_episode, 0.0))
    return dataclasses.replace(
        data,
        return_offset=(np.asarray(data.return_offset, np.float64) + shifts[0]).astype(np.float32),
        cost_offset=(np.asarray(data.cost_offset, np.float64) + shifts[1]).astype(np.float32),
    )
