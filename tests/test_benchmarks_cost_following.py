"""The cost-following benchmark's slope per doubling of the cost target, and its bar at 20."""

import numpy as np
import pytest

from benchmarks.cost_following import (
    COST_TARGETS,
    bar_at_20,
    doubling_slope,
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
