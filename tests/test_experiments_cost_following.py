"""experiments/cost_following.py: its bar at target 20, variant names and stale cells."""

from experiments.cost_following import (
    bar_at_20,
    return_label,
    same_experts,
    trained_variant,
    variant_name,
)


def test_the_bar_at_20_and_variant_names():
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


def test_frontier_rows_are_labelled_and_share_the_checkpoint():
    row = {"return_ratio": "frontier", "target_returns": [19.0, 28.0, 37.0, 37.0]}
    assert return_label(row) == "frontier 19.0/28.0/37.0/37.0"
    assert return_label({"return_ratio": 0.5}) == "0.5 R_ref"
    assert variant_name(trained_variant({"token_bins": 16, "returns": "frontier"})) == \
        "cpu+token_bins=16"
