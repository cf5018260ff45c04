"""Functional LoRA: structure, merge algebra, adapter-only gradients, vmap over adapter sets."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from safecdt_jax.model import (
    CDTConfig,
    apply_cdt,
    apply_cdt_lora,
    count_params,
    init_cdt,
    init_lora,
    lora_param_count,
    merge_lora,
)

CFG = CDTConfig.preset("tiny", obs_dim=5, act_dim=2, episode_len=30, num_layers=2)
K, D, R = CFG.seq_len, CFG.embed_dim, CFG.lora_rank
apply_base = jax.jit(lambda p, b: apply_cdt(p, CFG, b)["action_mean"])
apply_lora = jax.jit(lambda p, lo, b: apply_cdt_lora(p, lo, CFG, b)["action_mean"])


def make_batch(seed=0, b=3):
    rng = np.random.default_rng(seed)
    return {
        "states": jnp.asarray(rng.normal(size=(b, K, CFG.obs_dim)), jnp.float32),
        "actions": jnp.asarray(rng.uniform(-1, 1, size=(b, K, CFG.act_dim)), jnp.float32),
        "returns_to_go": jnp.asarray(rng.uniform(0, 4, size=(b, K)), jnp.float32),
        "costs_to_go": jnp.asarray(rng.uniform(0, 80, size=(b, K)), jnp.float32),
        "timesteps": jnp.asarray(np.arange(K)[None].repeat(b, 0), jnp.int32),
        "mask": jnp.ones((b, K), jnp.float32),
    }


def randomise_b(lora, key, std=0.3):
    """Adapters with non-zero B (at init B = 0 makes every adapter a no-op)."""
    leaves, tree = jax.tree.flatten(lora)
    keys = jax.random.split(key, len(leaves))
    new = [std * jax.random.normal(k, x.shape) if x.shape[0] == R else x
           for k, x in zip(keys, leaves, strict=True)]
    return jax.tree.unflatten(tree, new)


@pytest.fixture(scope="module")
def base():
    # Larger base weights than the 0.02 init, so adapter effects are clearly visible.
    p = init_cdt(jax.random.key(0), CFG)
    return jax.tree.map(lambda x: x * 10.0 if x.ndim == 2 else x, p)


def test_structure_and_init(base):
    lora = init_lora(jax.random.key(1), base, CFG)
    assert sorted(lora) == ["block_0", "block_1"]
    for name in lora:
        assert sorted(lora[name]["attn"]) == ["query", "value"]
        for ad in lora[name]["attn"].values():
            assert ad["A"].shape == (D, R) and ad["B"].shape == (R, D)
            assert not np.any(ad["B"]) and np.all(np.abs(ad["A"]) <= 1 / np.sqrt(D))
            assert np.std(ad["A"]) > 0.5 / np.sqrt(3 * D)  # uniform(+-1/sqrt(D)): std 1/sqrt(3D)
    assert count_params(lora) == lora_param_count(CFG) == 2 * 2 * 2 * D * R
    again = init_lora(jax.random.key(1), base, CFG)
    assert all(jax.tree.leaves(jax.tree.map(np.array_equal, lora, again)))
    other = init_lora(jax.random.key(2), base, CFG)
    assert not np.array_equal(lora["block_0"]["attn"]["query"]["A"],
                              other["block_0"]["attn"]["query"]["A"])


def test_merged_equals_base_at_init(base):
    lora = init_lora(jax.random.key(1), base, CFG)
    batch = make_batch()
    np.testing.assert_array_equal(apply_lora(base, lora, batch), apply_base(base, batch))


def test_merge_is_w_plus_scaled_ab_and_touches_only_targets(base):
    lora = randomise_b(init_lora(jax.random.key(1), base, CFG), jax.random.key(2))
    merged = merge_lora(base, lora, CFG)
    x = jax.random.normal(jax.random.key(3), (7, D))
    for name in ("block_0", "block_1"):
        for target in ("query", "value"):
            w = base[name]["attn"][target]["kernel"]
            a, b = lora[name]["attn"][target]["A"], lora[name]["attn"][target]["B"]
            direct = x @ w + CFG.lora_scale * ((x @ a) @ b)  # unmerged LoRA forward
            np.testing.assert_allclose(x @ merged[name]["attn"][target]["kernel"], direct,
                                       rtol=1e-5, atol=1e-5)
    changed = jax.tree.map(lambda p, m: not np.array_equal(p, m), base, merged)
    flat = {jax.tree_util.keystr(k): v for k, v in jax.tree_util.tree_flatten_with_path(changed)[0]}
    assert sorted(k for k, v in flat.items() if v) == sorted(
        f"['{n}']['attn']['{t}']['kernel']" for n in ("block_0", "block_1")
        for t in ("query", "value")
    )
    # merge is pure: the base params are not modified in place
    assert not np.array_equal(merged["block_0"]["attn"]["query"]["kernel"],
                              base["block_0"]["attn"]["query"]["kernel"])
    assert not np.allclose(apply_lora(base, lora, make_batch()), apply_base(base, make_batch()))


def test_merge_rejects_unknown_paths(base):
    with pytest.raises(KeyError):
        merge_lora(base, {"block_9": {"attn": {"query": {"A": 0, "B": 0}}}}, CFG)


def test_gradients_reach_adapters_only(base):
    batch = make_batch(4)
    target = jnp.zeros((3, K, CFG.act_dim))

    def loss(lora):
        return jnp.mean((apply_cdt_lora(base, lora, CFG, batch)["action_mean"] - target) ** 2)

    lora = init_lora(jax.random.key(1), base, CFG)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    first, grads = value_and_grad(lora)
    assert jax.tree.structure(grads) == jax.tree.structure(lora)
    for ad in [g for blk in grads.values() for g in blk["attn"].values()]:
        # B = 0 at init: dL/dA = g B^T vanishes, dL/dB = A^T g does not.
        assert not np.any(ad["A"]) and np.abs(ad["B"]).sum() > 0
    _, grads = value_and_grad(randomise_b(lora, jax.random.key(5)))
    assert all(np.abs(g).sum() > 0 for g in jax.tree.leaves(grads))

    # A few Adam steps on the adapters lower the loss and leave the base bit-identical.
    snapshot = jax.tree.map(np.array, base)
    tx = optax.adam(1e-2)

    @jax.jit
    def adam(lora, g, state):
        upd, state = tx.update(g, state)
        return optax.apply_updates(lora, upd), state

    state = tx.init(lora)
    for _ in range(5):
        lora, state = adam(lora, value_and_grad(lora)[1], state)
    assert float(value_and_grad(lora)[0]) < float(first)
    assert all(jax.tree.leaves(jax.tree.map(np.array_equal, snapshot, base)))


def test_vmap_over_adapter_sets_equals_loop(base):
    batch = make_batch(6)
    sets = [randomise_b(init_lora(jax.random.key(s), base, CFG), jax.random.key(10 + s))
            for s in range(3)]
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *sets)
    batched = jax.jit(jax.vmap(lambda lo: apply_cdt_lora(base, lo, CFG, batch)["action_mean"]))
    out = batched(stacked)
    assert out.shape == (3, 3, K, CFG.act_dim)
    for s, lo in enumerate(sets):
        np.testing.assert_allclose(out[s], apply_lora(base, lo, batch), rtol=1e-5, atol=1e-6)
    assert not np.allclose(out[0], out[1])
    # init_lora itself vmaps over keys: one adapter set per seed
    keys = jax.random.split(jax.random.key(7), 3)
    per_seed = jax.vmap(lambda k: init_lora(k, base, CFG))(keys)
    np.testing.assert_array_equal(per_seed["block_1"]["attn"]["value"]["A"][2],
                                  init_lora(keys[2], base, CFG)["block_1"]["attn"]["value"]["A"])
