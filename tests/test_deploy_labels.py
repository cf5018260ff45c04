"""Online labels of the deployment buffer (deploy/labels.py): the rules by hand, the windows that
read them, and the config that names them."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.data import buffer_add, buffer_init, sample_windows
from safecdt_jax.deploy import DeployConfig
from safecdt_jax.deploy.finetune import labelled_episodes
from safecdt_jax.deploy.labels import LABEL_RULES, online_labels, same_targets

T = 10  # steps of a full episode
# Five episodes: three under targets (4, 6), one under (4, 3), the last not run yet. Episode 1 was
# cut at the budget after 5 steps (cost 4 > B = 3), the others ran all 10 steps.
RETURNS = np.array([3.0, 1.0, 5.0, 2.0, 0.0], np.float32)
COSTS = np.array([2.0, 4.0, 0.0, 1.0, 0.0], np.float32)
LENGTHS = np.array([10, 5, 10, 10, 0], np.int32)
RTG = np.array([4.0, 4.0, 4.0, 4.0, 0.0], np.float32)
CTG = np.array([6.0, 6.0, 6.0, 3.0, 0.0], np.float32)
VALID = np.array([True, True, True, True, False])


def labels(rule):
    out = online_labels(rule, RETURNS, COSTS, LENGTHS, RTG, CTG, VALID, T)
    return tuple(np.asarray(x) for x in out)


def test_stage_labels_are_the_pooled_means_of_the_same_targets_by_hand():
    ret, cost = labels("stage")
    # Group (4, 6): 25 steps, return 9 and cost 6 -> per 10-step episode 3.6 and 2.4; the cut
    # episode counts for its 5 steps at the rate it ran them, not as a whole episode.
    np.testing.assert_allclose(ret, [3.6, 3.6, 3.6, 2.0, 0.0], rtol=1e-6)
    np.testing.assert_allclose(cost, [2.4, 2.4, 2.4, 1.0, 0.0], rtol=1e-6)


def test_a_group_of_cut_episodes_is_labelled_above_the_budget():
    ret, cost = online_labels("stage", [1.0, 2.0], [4.0, 4.0], [4, 8], [5.0, 5.0], [3.0, 3.0],
                              [True, True], T)
    np.testing.assert_allclose(np.asarray(cost), [80.0 / 12] * 2, rtol=1e-6)  # 8 in 12 steps
    np.testing.assert_allclose(np.asarray(ret), [2.5, 2.5], rtol=1e-6)


def test_target_and_hindsight_labels():
    ret, cost = labels("target")
    np.testing.assert_array_equal(ret, RTG * VALID)
    np.testing.assert_array_equal(cost, CTG * VALID)
    ret, cost = labels("hindsight")
    np.testing.assert_array_equal(ret, RETURNS * VALID)
    np.testing.assert_array_equal(cost, COSTS * VALID)


def test_same_targets_tolerates_rounding_and_ignores_invalid_episodes():
    same = np.asarray(same_targets([18.0, 18.0 + 1e-6, 18.0, 9.0], [30.0, 30.0, 30.0, 30.0],
                                   [True, True, False, True]))
    assert same[0].tolist() == [True, True, False, False]
    assert same[3].tolist() == [False, False, False, True]


def test_unknown_rule_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown LoRA label rule 'luck'"):
        online_labels("luck", RETURNS, COSTS, LENGTHS, RTG, CTG, VALID, T)
    with pytest.raises(ValueError, match=r"DeployConfig\.lora_labels must be one of"):
        DeployConfig(lora_labels="luck")


def test_windows_of_a_labelled_buffer_read_the_labels():
    """Constant targets: every step of every window reads its episode's label; without them the
    t = 0 step does and later steps fall by what was realised."""
    rng = np.random.default_rng(0)
    buf = buffer_init(5, T, 2, 1)
    for i in range(4):
        rewards = np.zeros(T, np.float32)
        rewards[: LENGTHS[i]] = RETURNS[i] / LENGTHS[i]
        costs = np.zeros(T, np.float32)
        costs[: int(COSTS[i])] = 1.0
        buf = buffer_add(buf, {"observations": rng.normal(size=(T, 2)),
                               "actions": rng.uniform(-1, 1, size=(T, 1)),
                               "rewards": rewards, "costs": costs}, LENGTHS[i])
    ret, cost = labels("stage")
    view = labelled_episodes(buf, (jnp.asarray(ret), jnp.asarray(cost)))
    win = sample_windows(jax.random.key(0), view, 64, 3, None, 1.0, 1.0, True)
    ep, valid = np.asarray(win.episode_index), np.asarray(win.mask) > 0
    np.testing.assert_allclose(np.asarray(win.returns_to_go)[valid],
                               np.broadcast_to(ret[ep][:, None], valid.shape)[valid], atol=1e-5)
    np.testing.assert_allclose(np.asarray(win.costs_to_go)[valid],
                               np.broadcast_to(cost[ep][:, None], valid.shape)[valid], atol=1e-5)
    win = sample_windows(jax.random.key(0), view, 64, 3, None, 1.0, 1.0, False)
    at_zero = np.asarray(win.start) == 0
    assert at_zero.any()
    np.testing.assert_allclose(np.asarray(win.costs_to_go)[at_zero, 0], cost[ep][at_zero],
                               atol=1e-5)


def test_every_rule_is_reachable_and_recorded_in_the_config():
    assert DeployConfig().lora_labels == "auto"
    for rule in LABEL_RULES:
        assert dataclasses.asdict(DeployConfig(lora_labels=rule))["lora_labels"] == rule


def test_auto_labels_are_target_for_a_sampling_cdt_and_stage_for_its_mean():
    from safecdt_jax.deploy.labels import resolve_label_rule

    assert DeployConfig().for_acting(True).lora_labels == "target"
    assert DeployConfig().for_acting(False).lora_labels == "stage"
    for rule in LABEL_RULES:  # a named rule is kept whatever the acting mode
        assert {resolve_label_rule(rule, acts) for acts in (True, False)} == {rule}
        assert DeployConfig(lora_labels=rule).for_acting(True).lora_labels == rule


def test_support_note_names_only_the_targets_outside():
    from safecdt_jax.deploy import make_variant
    from safecdt_jax.pretrain.support import requested_targets, support_note

    support = {"return": [2.0, 40.0], "cost": [12.7, 69.0]}
    assert support_note(support, [20.0], [18.0, 30.0]) is None
    assert support_note(None, [100.0], [0.0]) is None  # a checkpoint without a record
    note = support_note(support, [20.0, 50.0], [6.0, 18.0])
    assert note.startswith("note: cost targets 6 and return targets 50 lie outside")
    cfg = DeployConfig()
    runs = [(make_variant("safe_cdt"), 30.0), (make_variant("fixed_ctg(0.2)"), 30.0)]
    returns, costs = requested_targets(runs, cfg, reference_return=40.0)
    np.testing.assert_allclose(sorted(set(costs.tolist())), [1.5, 6.0, 30.0])  # CR 0.05, 0.2, 1
    np.testing.assert_allclose(returns, [20.0, 20.0])
