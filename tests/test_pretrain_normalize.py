"""Pretraining's input/output normalisation: its statistics, and the fold into the weights."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from safecdt_jax.cli import app
from safecdt_jax.data import load_dataset, make_dataset, write_dataset
from safecdt_jax.model import CDTConfig, init_cdt
from safecdt_jax.model.cdt import apply_cdt, dummy_batch, newest_action
from safecdt_jax.pretrain import (
    configs_from_meta,
    load_checkpoint,
    restore_state,
)
from safecdt_jax.pretrain.normalize import (
    IONorm,
    fit_io_norm,
    fold_io_norm,
    identity_norm,
    normalise_dataset,
)

CFG = CDTConfig.preset("tiny", 5, 2, 16)
NORM = IONorm(np.array([0.5, -1.0, 2.0, 0.0, 10.0], np.float32),
              np.array([0.01, 2.0, 0.5, 1.0, 4.0], np.float32),
              np.array([0.02, 0.5], np.float32))


def _dataset():
    """Two episodes: lengths 3 and 2 of a horizon 3 (one padded step)."""
    obs = np.array([[[1, 0], [3, 0], [5, 0]], [[7, 0], [9, 0], [99, 99]]], np.float32)
    act = np.array([[[0.01], [-0.02], [0.0]], [[0.005], [0.0], [7.0]]], np.float32)
    zeros = np.zeros((2, 3), np.float32)
    return make_dataset(obs, act, zeros, zeros, np.array([3, 2]))


def test_statistics_ignore_padding_and_floor_constant_sensors():
    norm = fit_io_norm(_dataset(), std_floor=0.01)
    np.testing.assert_allclose(norm.obs_mean, [5.0, 0.0])
    np.testing.assert_allclose(norm.obs_std, [np.sqrt(8.0), 0.01], rtol=1e-6)
    np.testing.assert_allclose(norm.act_scale, [0.02])  # not the padded 7.0
    only_actions = fit_io_norm(_dataset(), observations=False)
    assert only_actions.obs_mean.tolist() == [0, 0] and only_actions.obs_std.tolist() == [1, 1]
    np.testing.assert_allclose(only_actions.act_scale, [0.02])
    assert fit_io_norm(_dataset(), actions=False).act_scale.tolist() == [1.0]


def test_normalised_dataset_keeps_padding_zero():
    data = _dataset()
    assert data.valid_steps.tolist() == [[True, True, True], [True, True, False]]
    norm = fit_io_norm(data)
    out = normalise_dataset(data, norm)
    np.testing.assert_allclose(out.observations[0, :, 0], (np.array([1, 3, 5]) - 5) / np.sqrt(8),
                               rtol=1e-6)
    np.testing.assert_allclose(out.actions[:, :, 0], [[0.5, -1.0, 0.0], [0.25, 0.0, 0.0]])
    assert out.observations[1, 2].tolist() == [0.0, 0.0]
    np.testing.assert_array_equal(out.lengths, data.lengths)


def test_json_round_trip():
    back = IONorm.from_json(NORM.to_json())
    for a, b in zip(back, NORM, strict=True):
        np.testing.assert_array_equal(a, b)


def test_folded_params_compute_the_same_function_of_raw_inputs():
    key = jax.random.key(0)
    # Perturb the init so that every bias and LayerNorm is non-trivial.
    params = jax.tree.map(lambda x: x + 0.1 * jax.random.normal(key, x.shape), init_cdt(key, CFG))
    rng = np.random.default_rng(0)
    raw = dummy_batch(CFG, 3)
    raw["states"] = jnp.asarray(rng.normal(size=raw["states"].shape) * 3, jnp.float32)
    raw["actions"] = jnp.asarray(rng.uniform(-0.02, 0.02, raw["actions"].shape), jnp.float32)
    normed = dict(raw, states=(raw["states"] - NORM.obs_mean) / NORM.obs_std,
                  actions=raw["actions"] / NORM.act_scale)
    inner = apply_cdt(params, CFG, normed)
    folded = fold_io_norm(params, NORM)
    outer = apply_cdt(folded, CFG, raw)
    tol = dict(rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(outer["action_mean"], inner["action_mean"] * NORM.act_scale, **tol)
    np.testing.assert_allclose(outer["action_log_std"],
                               inner["action_log_std"] + np.log(NORM.act_scale), **tol)
    np.testing.assert_allclose(outer["next_state"],
                               inner["next_state"] * NORM.obs_std + NORM.obs_mean, rtol=1e-5,
                               atol=1e-5)
    np.testing.assert_allclose(outer["cost_log_probs"], inner["cost_log_probs"], **tol)
    # The trimmed inference pass reads the same folded weights.
    np.testing.assert_allclose(newest_action(folded, CFG, raw),
                               jnp.clip(outer["action_mean"][:, -1], -1, 1), **tol)
    same = fold_io_norm(params, identity_norm(5, 2))
    for a, b in zip(jax.tree.leaves(same), jax.tree.leaves(params), strict=True):
        np.testing.assert_array_equal(a, b)


def _car_like_file(tmp_path):
    """Actions within +-0.02 and sensors offset by 5: what normalisation is for."""
    rng = np.random.default_rng(1)
    obs = (5.0 + rng.normal(size=(24, 16, 5))).astype(np.float32)
    w = rng.normal(size=(5, 2)) / np.sqrt(5)
    actions = (0.02 * np.tanh((obs - 5.0) @ w)).astype(np.float32)
    rewards = rng.uniform(0, 1, (24, 16)).astype(np.float32)
    costs = (rng.uniform(size=(24, 16)) < 0.1).astype(np.float32)
    path = tmp_path / "car_like.hdf5"
    write_dataset(path, make_dataset(obs, actions, rewards, costs, np.full(24, 16),
                                     attrs={"task": "Synthetic"}))
    return path


@pytest.mark.parametrize("normalize", [True, False])
def test_checkpoint_records_and_folds_the_normalisation(tmp_path, normalize):
    """Through the CLI: the normalisation flags reach the checkpoint, which loads folded."""
    path, out = _car_like_file(tmp_path), tmp_path / "ckpt"
    flags = ["--set", "scale_actions=true", "--set", "standardize_obs=true"] if normalize else []
    args = ["pretrain", "--data", str(path), "--preset", "tiny", "--steps", "20", "--batch",
            "16", "--set", "chunk=20", "--out", str(out), *flags]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    ckpt = load_checkpoint(out)
    _, optim, cfg = configs_from_meta(ckpt.meta)
    assert cfg.scale_actions == cfg.standardize_obs == normalize
    assert ("io_norm" in ckpt.meta) == normalize
    trained = restore_state(out, ckpt.cfg, optim).params
    if normalize:
        norm = IONorm.from_json(ckpt.meta["io_norm"])
        for a, b in zip(norm, fit_io_norm(load_dataset(path)), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6)
        assert 0.015 < norm.act_scale.min() <= norm.act_scale.max() <= 0.02
        trained = fold_io_norm(trained, norm)
    for a, b in zip(jax.tree.leaves(ckpt.params), jax.tree.leaves(trained), strict=True):
        np.testing.assert_array_equal(a, b)


