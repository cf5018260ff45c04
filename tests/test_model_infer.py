"""The trimmed evaluation pass (`newest_only`) equals the full model's newest action."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.model import (
    CDTConfig,
    apply_cdt,
    init_cdt,
    last_action,
    newest_action,
    with_nominal_edges,
)


@pytest.mark.parametrize("preset,layers", [("tiny", 1), ("tiny", 3), ("cpu", 2)])
def test_newest_action_equals_last_action(preset, layers):
    cfg = with_nominal_edges(CDTConfig.preset(preset, 7, 2, 50, num_layers=layers))
    params = init_cdt(jax.random.PRNGKey(1), cfg)
    # Non-trivial LayerNorms and biases, so every parameter matters.
    params = jax.tree.map(lambda p: p + 0.05 * jax.random.normal(jax.random.PRNGKey(2), p.shape),
                          params)
    b, k = 5, cfg.seq_len
    ks = jax.random.split(jax.random.PRNGKey(3), 5)
    n_valid = jnp.array([1, 2, k - 1, k, k])  # left padding of every length, and none
    mask = (jnp.arange(k)[None] >= k - n_valid[:, None]).astype(jnp.float32)
    batch = {
        "states": jax.random.normal(ks[0], (b, k, 7)),
        "actions": jax.random.uniform(ks[1], (b, k, 2), minval=-1, maxval=1),
        "returns_to_go": jax.random.uniform(ks[2], (b, k), maxval=5),
        "costs_to_go": jax.random.uniform(ks[3], (b, k), maxval=40),
        "timesteps": jax.random.randint(ks[4], (b, k), 0, 50),
        "mask": mask,
    }
    batch["states"] = jnp.where(mask[..., None] > 0, batch["states"], jnp.nan)  # padding ignored
    np.testing.assert_allclose(newest_action(params, cfg, batch), last_action(params, cfg, batch),
                               rtol=2e-5, atol=2e-6)


def _batch(cfg, b=4):
    ks = jax.random.split(jax.random.PRNGKey(3), 3)
    k = cfg.seq_len
    return {"states": jax.random.normal(ks[0], (b, k, cfg.obs_dim)),
            "actions": jax.random.uniform(ks[1], (b, k, cfg.act_dim), minval=-1, maxval=1),
            "returns_to_go": jax.random.uniform(ks[2], (b, k), maxval=5),
            "costs_to_go": jnp.full((b, k), 10.0), "timesteps": jnp.tile(jnp.arange(k), (b, 1)),
            "mask": jnp.ones((b, k))}


def test_stochastic_action_is_a_sample_of_the_gaussian_head():
    cfg = CDTConfig.preset("tiny", 7, 2, 50).replace(stochastic_actions=True)
    params = init_cdt(jax.random.PRNGKey(1), cfg)
    batch = _batch(cfg)
    out = apply_cdt(params, cfg, batch)
    mean, log_std = out["action_mean"][:, -1], out["action_log_std"][:, -1]
    key = jax.random.PRNGKey(9)
    expected = np.clip(mean + np.exp(log_std) * jax.random.normal(key, mean.shape), -1, 1)
    np.testing.assert_allclose(newest_action(params, cfg, batch, key), expected, rtol=2e-5,
                               atol=2e-6)
    np.testing.assert_array_equal(newest_action(params, cfg, batch, key),
                                  newest_action(params, cfg, batch, key))  # same key, same bits
    assert not np.allclose(newest_action(params, cfg, batch, jax.random.PRNGKey(10)), expected)
    # A vanishing std gives the mean action back.
    narrow = {**params, "action_log_std": {**params["action_log_std"],
                                           "bias": jnp.full((2,), -30.0)}}
    np.testing.assert_allclose(newest_action(narrow, cfg, batch, key),
                               np.clip(mean, -1, 1), rtol=2e-5, atol=2e-6)


def test_stochastic_action_without_a_key_is_an_error():
    cfg = CDTConfig.preset("tiny", 7, 2, 50).replace(stochastic_actions=True)
    params = init_cdt(jax.random.PRNGKey(1), cfg)
    with pytest.raises(ValueError, match="stochastic_actions needs a PRNG key"):
        newest_action(params, cfg, _batch(cfg))
    with pytest.raises(ValueError, match="stochastic_actions"):
        CDTConfig.preset("tiny", 7, 2, 50).replace(stochastic_actions=1)
