"""The trimmed evaluation pass (`newest_only`) equals the full model's newest action."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.model import CDTConfig, init_cdt, last_action, newest_action


@pytest.mark.parametrize("preset,layers", [("tiny", 1), ("tiny", 3), ("cpu", 2)])
def test_newest_action_equals_last_action(preset, layers):
    cfg = CDTConfig.preset(preset, 7, 2, 50, num_layers=layers)
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
