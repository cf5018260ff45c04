"""safecdt_jax.stats: the experiments' bootstrap intervals, frontier and spreads, by hand."""

import numpy as np
import pytest

from safecdt_jax.stats import (
    doubling_slope,
    frontier_returns,
    per_seed_metrics,
    ratio_interval,
    seed_spread,
)

COST_TARGETS = (10.0, 20.0, 40.0, 80.0)  # the cost-following check's targets


# The sim2sim transfer table's interval of a ratio of means.


def test_constant_samples_give_the_exact_ratio():
    assert ratio_interval(np.full(5, 3.0), np.full(7, 1.5)) == (2.0, 2.0)


def test_interval_holds_the_point_ratio_and_narrows_with_episodes():
    rng = np.random.default_rng(1)
    few = ratio_interval(rng.exponential(20.0, 32), rng.exponential(20.0, 32))
    many = ratio_interval(rng.exponential(20.0, 2048), rng.exponential(20.0, 2048))
    assert few[0] < 1.0 < few[1] and many[0] < 1.0 < many[1]
    assert many[1] - many[0] < 0.25 * (few[1] - few[0])


def test_heavy_tail_of_32_episodes_spans_a_factor_of_two():
    # Circle-like costs: mostly 0, a few escapes of ~260 steps each; same law on both sides.
    rng = np.random.default_rng(0)
    sample = lambda: np.where(rng.random(32) < 0.1, 260.0, 0.0)
    lo, hi = ratio_interval(sample(), sample())
    assert hi / lo > 2.0


def test_zero_denominator_resamples_end_at_inf():
    lo, hi = ratio_interval(np.ones(4), np.array([0.0, 0.0, 0.0, 1.0]))
    assert hi == np.inf and lo > 0


def test_empty_sample_is_an_error():
    with pytest.raises(ValueError, match="at least one episode"):
        ratio_interval(np.array([]), np.ones(3))


# The cost-following check's slope per doubling of the cost target, and the data's frontier.


def test_slope_of_a_model_that_follows_exactly():
    # 5 cost steps more per doubling of the target, the same in every episode: no spread.
    costs = np.repeat((5.0 * np.log2(COST_TARGETS))[:, None], 20, axis=1)
    got = doubling_slope(COST_TARGETS, costs)
    assert got["slope"] == pytest.approx(5.0) and got["low"] == pytest.approx(5.0)
    assert got["high"] == pytest.approx(5.0)


def test_a_target_blind_model_gets_an_interval_around_zero():
    costs = np.random.default_rng(0).normal(40.0, 25.0, size=(4, 20))
    got = doubling_slope(COST_TARGETS, costs, seed=1)
    assert got["low"] < 0.0 < got["high"]
    assert doubling_slope(COST_TARGETS, costs, seed=1) == got  # same seed -> same interval


def test_slope_of_bad_shapes_is_an_error():
    with pytest.raises(ValueError, match="doubling_slope"):
        doubling_slope(COST_TARGETS, np.zeros((3, 5)))


def test_frontier_returns_by_hand():
    returns = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    costs = np.array([0.0, 5.0, 15.0, 30.0, 100.0])
    # Cost <= 10: returns 10, 20 -> 90th percentile 19; <= 20: 10-30 -> 28; <= 40 and 80: 37.
    assert frontier_returns(returns, costs, COST_TARGETS) == pytest.approx(
        [19.0, 28.0, 37.0, 37.0])
    assert frontier_returns(returns, costs, COST_TARGETS, q=100.0) == pytest.approx(
        [20.0, 30.0, 40.0, 40.0])
    with pytest.raises(ValueError, match="no episode of the data costs at most 10"):
        frontier_returns(returns, costs + 11.0, COST_TARGETS)
    with pytest.raises(ValueError, match="one shape"):
        frontier_returns(returns, costs[:3], COST_TARGETS)


# The levers experiment's per-seed metrics and its two spreads.


def test_per_seed_metrics_and_drift_by_hand():
    cost = np.zeros((2, 50))
    cost[0, -10:] = 31.0  # seed 0 violates in its last 10 episodes, seed 1 never
    run = {"metrics": {"cost": cost.tolist(), "violation": (cost > 30).tolist(),
                       "return": np.ones((2, 50)).tolist()}}
    m = per_seed_metrics(run)
    np.testing.assert_allclose(m["vr"], [20.0, 0.0])
    np.testing.assert_allclose(m["cost"], [6.2, 0.0])
    np.testing.assert_allclose(m["late"], [31.0, 0.0])
    np.testing.assert_allclose(m["drift"], [31.0, 0.0])
    np.testing.assert_allclose(m["reward"], [1.0, 1.0])


def test_spread_separates_checkpoints_from_seeds():
    s = seed_spread([np.array([1.0, 3.0]), np.array([5.0, 7.0])])  # ckpt means 2 and 6
    assert s == pytest.approx({"mean": 4.0, "ckpt_std": 2.0, "seed_std": 1.0})
