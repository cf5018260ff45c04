"""Pareto-frontier relabelling: copies differ from their sources only by constant RTG/CTG shifts."""

import dataclasses

import jax
import numpy as np
import pytest

from safecdt_jax.data import (
    RelabelConfig,
    costs_to_go,
    episode_costs,
    episode_returns,
    grid_filter,
    make_dataset,
    pareto_front,
    policy_mean_labels,
    relabel_pareto,
    returns_to_go,
    sample_windows,
)

T = 10


def line_data(seed=0):
    """Episode costs 0..9; per cost, 4 identical episodes on the front R = 2C and 6 below it."""
    rng = np.random.default_rng(seed)
    totals = []
    for c in range(10):
        totals += [(c, 2.0 * c)] * 4 + [(c, 2.0 * c - rng.uniform(1, 5)) for _ in range(6)]
    n = len(totals)
    costs = np.zeros((n, T), np.float32)
    rewards = np.zeros((n, T), np.float32)
    lengths = rng.integers(T - 2, T + 1, size=n)
    for i, (c, r) in enumerate(totals):
        costs[i, :c] = 1.0
        rewards[i, : lengths[i]] = r / lengths[i]
    return make_dataset(
        rng.normal(size=(n, T, 3)),
        rng.uniform(-1, 1, (n, T, 2)),
        rewards,
        costs,
        lengths,
        episode_info={"knob": np.arange(n)},
    )


CFG = RelabelConfig(max_reward=100.0)


def test_copies_only_shift_rtg_and_ctg_by_constants():
    data = line_data()
    out = relabel_pareto(jax.random.key(0), data, CFG)
    n0 = data.n_episodes
    source = out.episode_info["relabel_source"]
    copies = np.arange(n0, out.n_episodes)
    assert copies.size == 8  # int(0.2 * 40): the 40 front episodes survive the grid filter
    np.testing.assert_array_equal(source[:n0], -1)
    for k in (
        "observations",
        "next_observations",
        "actions",
        "rewards",
        "costs",
        "lengths",
        "terminals",
        "timeouts",
        "return_offset",
        "cost_offset",
    ):
        np.testing.assert_array_equal(getattr(out, k)[:n0], getattr(data, k), err_msg=k)
        if k not in ("return_offset", "cost_offset"):
            np.testing.assert_array_equal(
                getattr(out, k)[copies], getattr(data, k)[source[copies]], err_msg=k
            )
    np.testing.assert_array_equal(out.episode_info["knob"][copies], source[copies])

    valid = np.arange(T)[None, :] < out.lengths[copies][:, None]
    for fn, offset in ((returns_to_go, out.return_offset), (costs_to_go, out.cost_offset)):
        diff = np.asarray(fn(out))[copies] - np.asarray(fn(data))[source[copies]]
        np.testing.assert_allclose(diff, np.where(valid, offset[copies][:, None], 0), atol=1e-4)
    assert np.all(out.cost_offset[copies] >= 0)  # a copy never claims a smaller budget


def test_targets_lie_on_cost_grid_and_above_the_front():
    out = relabel_pareto(np.random.default_rng(3), line_data(), CFG)
    copies = np.arange(100, out.n_episodes)
    c, r = episode_costs(out)[copies], episode_returns(out)[copies]
    # Cost targets: linspace over the filtered episodes' cost range, in order.
    np.testing.assert_allclose(c, np.linspace(0, 9, copies.size), atol=1e-5)
    # Return targets: uniform in [f(c) + min_reward, max_reward] with the front f(c) = 2c.
    assert np.all(r >= 2 * c + CFG.min_reward - 1e-3) and np.all(r <= CFG.max_reward + 1e-3)
    src_c = episode_costs(line_data())[out.episode_info["relabel_source"][copies]]
    assert np.all(src_c <= c + 1e-6)  # each copy comes from an episode at most as costly


def test_windows_on_copies_carry_shifted_returns():
    out = relabel_pareto(0, line_data(), CFG)
    target = out.n_episodes - 1
    weights = np.zeros(out.n_episodes, np.float32)
    weights[target] = 1.0
    w = sample_windows(jax.random.key(0), out, batch=16, K=3, weights=weights)
    t = np.minimum(np.asarray(w.timesteps), T - 1)
    mask = np.asarray(w.mask) > 0
    want = np.asarray(returns_to_go(out))[target][t] * 0.1
    np.testing.assert_allclose(w.returns_to_go, np.where(mask, want, 0), rtol=1e-5, atol=1e-6)
    want = np.asarray(costs_to_go(out))[target][t]
    np.testing.assert_allclose(w.costs_to_go, np.where(mask, want, 0), rtol=1e-5, atol=1e-6)


def test_same_key_same_result_and_disabled_is_identity():
    data = line_data()
    a = relabel_pareto(jax.random.key(5), data, CFG)
    b = relabel_pareto(jax.random.key(5), data, CFG)
    np.testing.assert_array_equal(
        a.episode_info["relabel_source"], b.episode_info["relabel_source"]
    )
    np.testing.assert_array_equal(a.return_offset, b.return_offset)
    assert relabel_pareto(0, data, RelabelConfig(enabled=False)) is data
    # Too few episodes per grid cell: nothing survives the filter, nothing is added.
    assert relabel_pareto(0, data, RelabelConfig(min_per_bin=5)) is data


def test_pareto_front_known_points():
    c = [0, 1, 2, 2, 3, 1]
    r = [1, 3, 2, 4, 4, 3]
    # (2,2) is dominated by (1,3); (3,4) by (2,4); the duplicate (1,3) points are both kept.
    np.testing.assert_array_equal(pareto_front(c, r), [0, 1, 3, 5])


def test_grid_filter_caps_and_drops_bins():
    # Costs 0 and 1 in separate cost bins, one reward bin: 15 episodes at cost 0, 2 at cost 1,
    # 3 at cost 2.
    costs = np.array([0.0] * 15 + [1.0] * 2 + [2.0] * 3)
    returns = np.zeros(20)
    cfg = RelabelConfig(cost_bins=3, reward_bins=1)
    kept = grid_filter(np.random.default_rng(0), costs, returns, cfg)
    assert np.sum(costs[kept] == 0) == cfg.max_per_bin  # capped at 10
    assert np.sum(costs[kept] == 1) == 0  # <= 2 episodes: dropped
    np.testing.assert_array_equal(kept[costs[kept] == 2], [17, 18, 19])
    assert len(set(kept.tolist())) == kept.size


@pytest.mark.parametrize("deg", [0, 3])
def test_degree_choice_still_gives_valid_copies(deg):
    out = relabel_pareto(1, line_data(), RelabelConfig(deg=deg, max_reward=100.0))
    copies = np.arange(100, out.n_episodes)
    assert copies.size == 8 and np.all(np.isfinite(out.return_offset))
    assert np.all(out.cost_offset[copies] >= 0)


def test_policy_mean_labels_shift_each_episode_to_its_policy_mean():
    # Three episodes of policy 7 cost 1, 2 and 6 (mean 3) and return 2, 4, 6 (mean 4); one of
    # policy 9 keeps its own labels.
    costs = np.zeros((4, T), np.float32)
    for i, c in enumerate((1, 2, 6, 4)):
        costs[i, :c] = 1.0
    rewards = np.tile(np.array([[0.2], [0.4], [0.6], [0.5]], np.float32), (1, T))
    data = make_dataset(np.zeros((4, T, 3)), np.zeros((4, T, 2)), rewards, costs,
                        np.full(4, T), episode_info={"snapshot": np.array([7, 7, 7, 9])})
    out = policy_mean_labels(data)
    np.testing.assert_allclose(episode_costs(out), [3, 3, 3, 4], atol=1e-6)
    np.testing.assert_allclose(episode_returns(out), [4, 4, 4, 5], atol=1e-5)
    # Within an episode the tokens still fall by the realised costs: episode 0 (cost 1, label 3)
    # keeps 2 of its budget at the end, episode 2 (cost 6) ends 3 over it.
    ctg = np.asarray(costs_to_go(out))
    np.testing.assert_allclose(ctg[:, 0] - ctg[:, -1], [1, 2, 6, 4], atol=1e-6)
    np.testing.assert_allclose(ctg[[0, 2], -1], [2, -3], atol=1e-6)
    for f in ("observations", "actions", "rewards", "costs", "lengths"):
        np.testing.assert_array_equal(getattr(out, f), getattr(data, f))


def test_policy_mean_labels_read_the_means_recorded_before_filtering():
    # Policy 7 is careful: of its 4 rollouts (costs 0, 0, 0, 8: mean 2) a filter kept only the
    # costly one. Labelled with the recorded mean (2), not the kept episode's 8.
    costs = np.zeros((2, T), np.float32)
    costs[0, :8] = 1.0
    costs[1, :4] = 1.0
    rewards = np.full((2, T), 0.1, np.float32)
    info = {"snapshot": np.array([7, 9]), "policy_cost": np.array([2.0, 4.0], np.float32),
            "policy_return": np.array([1.5, 1.0], np.float32)}
    data = make_dataset(np.zeros((2, T, 3)), np.zeros((2, T, 2)), rewards, costs,
                        np.full(2, T), episode_info=info)
    out = policy_mean_labels(data)
    np.testing.assert_allclose(episode_costs(out), [2, 4], atol=1e-6)
    np.testing.assert_allclose(episode_returns(out), [1.5, 1.0], atol=1e-5)
    grouped = dataclasses.replace(data, episode_info={"run": info["snapshot"], **{
        k: v for k, v in info.items() if k != "snapshot"}})  # other groups: their own means
    np.testing.assert_allclose(episode_costs(policy_mean_labels(grouped, key="run")), [8, 4],
                               atol=1e-6)


def test_policy_mean_labels_name_the_missing_key():
    with pytest.raises(ValueError, match="episode_info\\['snapshot'\\]"):
        policy_mean_labels(line_data())
