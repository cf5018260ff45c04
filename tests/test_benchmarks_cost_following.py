"""The cost-following benchmark's slope per doubling of the cost target, and its bar at 20."""

import numpy as np
import pytest

from benchmarks.cost_following import (
    COST_TARGETS,
    bar_at_20,
    doubling_slope,
    frontier_returns,
    return_label,
    same_experts,
    trained_variant,
    variant_name,
)


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


def test_bad_shapes_and_the_bar_at_20():
    with pytest.raises(ValueError, match="doubling_slope"):
        doubling_slope(COST_TARGETS, np.zeros((3, 5)))
    assert bar_at_20(34.0) == 34.0 and bar_at_20(0.0) == 20.0
    assert variant_name({}) == "cpu"
    assert variant_name({"token_bins": 16, "labels": "policy"}) == \
        "cpu+labels=policy+token_bins=16"


def test_acting_stochastically_shares_the_pretrained_checkpoint():
    variant = {"actions": "sampled", "stochastic_actions": True}
    assert variant_name(variant) == "cpu+actions=sampled+stochastic_actions=True"
    assert variant_name(trained_variant(variant)) == "cpu+actions=sampled"
    assert trained_variant({"token_bins": 16}) == {"token_bins": 16}


def test_cells_of_retrained_experts_are_stale():
    from safecdt_jax.experts.collect import snapshot_path, snapshot_sha256

    committed = snapshot_sha256(snapshot_path("PointCircle1"))
    # The Point's cells record 'executed' whatever was asked, so the hash must decide.
    cell = {"task": "PointCircle1", "data": {"actions": "executed", "snapshot_sha256": committed}}
    assert same_experts(cell)
    assert not same_experts({**cell, "data": {**cell["data"], "snapshot_sha256": "0" * 64}})
    assert same_experts({"task": "PointCircle1", "data": {}})  # scripted data: no hash


def test_frontier_returns_by_hand():
    returns = np.array([10.0, 20.0, 30.0, 40.0, 50.0])
    costs = np.array([0.0, 5.0, 15.0, 30.0, 100.0])
    # Cost <= 10: returns 10, 20 -> 90th percentile 19; <= 20: 10-30 -> 28; <= 40 and 80: 37.
    assert frontier_returns(returns, costs) == pytest.approx([19.0, 28.0, 37.0, 37.0])
    assert frontier_returns(returns, costs, q=100.0) == pytest.approx([20.0, 30.0, 40.0, 40.0])
    with pytest.raises(ValueError, match="no episode of the data costs at most 10"):
        frontier_returns(returns, costs + 11.0)
    with pytest.raises(ValueError, match="one shape"):
        frontier_returns(returns, costs[:3])
    row = {"return_ratio": "frontier", "target_returns": [19.0, 28.0, 37.0, 37.0]}
    assert return_label(row) == "frontier 19.0/28.0/37.0/37.0"
    assert return_label({"return_ratio": 0.5}) == "0.5 R_ref"
    assert variant_name(trained_variant({"token_bins": 16, "returns": "frontier"})) == \
        "cpu+token_bins=16"
