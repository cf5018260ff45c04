"""OSRL's CDT loss, the temperature loss, the optimisers and a few training steps."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.model import (
    CDTConfig,
    OptimConfig,
    batch_gradients,
    cdt_loss,
    init_cdt,
    init_train_state,
    learning_rate_schedule,
    loss_normalisers,
    make_optimizer,
    make_train_step,
    micro_batches,
)
from safecdt_jax.model.loss import temperature_loss
from safecdt_jax.pretrain import PretrainConfig

CFG = CDTConfig.preset("tiny", obs_dim=5, act_dim=2, episode_len=30)
K = CFG.seq_len
LOG_T = jnp.log(0.1)
loss_fn = jax.jit(cdt_loss, static_argnums=2)


def make_batch(seed=0, lengths=(4, 2, 3)):
    """Right-padded training windows (as sampled past an episode's end): mask 0 at the tail."""
    rng = np.random.default_rng(seed)
    b = len(lengths)
    mask = (np.arange(K)[None] < np.array(lengths)[:, None]).astype(np.float32)
    return {
        "states": jnp.asarray(rng.normal(size=(b, K, CFG.obs_dim)), jnp.float32),
        "actions": jnp.asarray(rng.uniform(-1, 1, size=(b, K, CFG.act_dim)), jnp.float32),
        "returns_to_go": jnp.asarray(rng.uniform(0, 4, size=(b, K)), jnp.float32),
        "costs_to_go": jnp.asarray(rng.uniform(0, 80, size=(b, K)), jnp.float32),
        "costs": jnp.asarray(rng.integers(0, 2, size=(b, K)), jnp.float32),
        "timesteps": jnp.asarray(np.arange(K)[None].repeat(b, 0) + 3, jnp.int32),
        "mask": jnp.asarray(mask),
    }


@pytest.fixture(scope="module")
def params():
    return init_cdt(jax.random.key(0), CFG)


def zero_heads(params):
    """Zero heads: mean 0, log_std 0, cost probabilities (1/2, 1/2), next-state prediction 0."""
    out = dict(params)
    for head in ("action_mean", "action_log_std", "cost_head", "state_head"):
        out[head] = jax.tree.map(jnp.zeros_like, params[head])
    return out


def test_known_value_with_zero_heads(params):
    batch = make_batch(1)
    loss, aux = loss_fn(zero_heads(params), LOG_T, CFG, batch, None)
    mask = np.asarray(batch["mask"])
    a = np.asarray(batch["actions"])
    half_log_2pi = 0.5 * math.log(2 * math.pi)
    # N(0, 1) log-density per dimension, averaged over valid steps x action dims
    ll = (((-0.5 * a**2 - half_log_2pi) * mask[..., None]).sum()) / (mask.sum() * 2)
    entropy = 0.5 + half_log_2pi
    act_loss = -(ll + 0.1 * entropy)
    cost_loss = math.log(2.0) * mask.sum() / mask.size  # padded positions in the denominator
    np.testing.assert_allclose(aux["log_likelihood"], ll, rtol=1e-5)
    np.testing.assert_allclose(aux["entropy"], entropy, rtol=1e-6)
    np.testing.assert_allclose(aux["act_loss"], act_loss, rtol=1e-5)
    np.testing.assert_allclose(aux["cost_loss"], cost_loss, rtol=1e-5)
    np.testing.assert_allclose(aux["temperature"], 0.1, rtol=1e-6)
    np.testing.assert_allclose(loss, act_loss + 0.02 * cost_loss, rtol=1e-5)
    # next-state MSE (weight 0 by default): zero head -> mean of s_{t+1}^2 over valid pairs
    pair = mask[:, :-1] * mask[:, 1:]
    s_next = np.asarray(batch["states"])[:, 1:]
    state_loss = (s_next**2 * pair[..., None]).sum() / (pair.sum() * CFG.obs_dim)
    np.testing.assert_allclose(aux["state_loss"], state_loss, rtol=1e-5)


def test_cost_accuracy_known_value(params):
    batch = make_batch(2)
    p = zero_heads(params)
    p["cost_head"] = dict(p["cost_head"], bias=jnp.array([1.0, 0.0]))  # always predicts "cost 0"
    _, aux = loss_fn(p, LOG_T, CFG, batch, None)
    mask, costs = np.asarray(batch["mask"]), np.asarray(batch["costs"])
    np.testing.assert_allclose(aux["cost_accuracy"], ((costs == 0) * mask).sum() / mask.sum(),
                               rtol=1e-6)


def test_loss_is_finite_and_deterministic(params):
    batch = make_batch(3)
    loss, aux = loss_fn(params, LOG_T, CFG, batch, jax.random.key(4))
    assert np.isfinite(loss) and all(np.isfinite(v) for v in aux.values())
    again, _ = loss_fn(params, LOG_T, CFG, batch, jax.random.key(4))
    other, _ = loss_fn(params, LOG_T, CFG, batch, jax.random.key(5))
    assert float(again) == float(loss) != float(other)  # same key -> same bits; dropout is on


def test_padded_positions_do_not_change_loss(params):
    batch = make_batch(5)
    pad = np.asarray(batch["mask"])[..., None] == 0
    key = jax.random.key(6)
    base, _ = loss_fn(params, LOG_T, CFG, batch, key)
    junk = dict(batch, actions=jnp.where(pad, 123.0, batch["actions"]),
                costs=jnp.where(pad[..., 0], 1.0, batch["costs"]))
    np.testing.assert_array_equal(loss_fn(params, LOG_T, CFG, junk, key)[0], base)
    valid = dict(batch, actions=batch["actions"].at[0, 0].add(0.5))  # a valid action matters
    assert float(loss_fn(params, LOG_T, CFG, valid, key)[0]) != float(base)


def test_temperature_loss_and_gradient():
    entropy = jnp.asarray(1.3)
    lt = jnp.log(0.2)
    np.testing.assert_allclose(temperature_loss(lt, entropy, CFG), 0.2 * (1.3 + 2.0), rtol=1e-6)
    g_lt, g_h = jax.grad(temperature_loss, argnums=(0, 1))(lt, entropy, CFG)
    np.testing.assert_allclose(g_lt, 0.2 * 3.3, rtol=1e-5)
    assert float(g_h) == 0.0  # H is stopped


def test_model_gradient_ignores_temperature(params):
    """T enters the act loss with a stopped gradient."""
    batch = make_batch(7)
    g, _ = jax.jit(jax.grad(cdt_loss, argnums=1, has_aux=True), static_argnums=2)(
        params, LOG_T, CFG, batch, None)
    assert float(g) == 0.0


def test_optimizer_warmup_schedule():
    schedule = learning_rate_schedule(OptimConfig())
    got = [float(schedule(jnp.asarray(s))) for s in (0, 249, 498, 499, 10_000)]
    np.testing.assert_allclose(got, [1e-4 / 500, 0.5e-4, 1e-4 * 499 / 500, 1e-4, 1e-4], rtol=1e-5)
    txs = make_optimizer(OptimConfig())
    p = {"w": jnp.zeros(3)}
    g = {"w": jnp.full(3, 0.01)}  # below the clip norm; zero params: no decay contribution
    upd, _ = jax.jit(txs.model.update)(g, txs.model.init(p), p)
    # Adam's first step moves every coordinate by lr_0 = 1e-4 * 1/500 (the schedule is used).
    np.testing.assert_allclose(upd["w"], -1e-4 / 500, rtol=1e-3)
    t0 = jnp.asarray(0.0)
    t_upd, _ = jax.jit(txs.temperature.update)(jnp.asarray(2.0), txs.temperature.init(t0))
    np.testing.assert_allclose(t_upd, -1e-4, rtol=1e-3)  # plain Adam, lr 1e-4, no warmup


def test_gradient_clipping_and_weight_decay():
    """Second AdamW step, computed by hand: clip to norm 0.25 first, decay lr * wd * p after."""
    lr, wd, eps = 1e-4, 1e-4, 1e-8
    txs = make_optimizer(OptimConfig(warmup_steps=1))
    p = {"w": jnp.ones(2)}
    g1, g2 = np.array([3.0, 4.0]), np.array([0.03, 0.04])  # norm 5 (clipped), norm 0.05 (not)
    update = jax.jit(txs.model.update)
    _, state = update({"w": jnp.asarray(g1)}, txs.model.init(p), p)
    upd, _ = update({"w": jnp.asarray(g2)}, state, p)
    g1c = g1 * 0.25 / 5.0
    m = 0.9 * (0.1 * g1c) + 0.1 * g2
    v = 0.999 * (0.001 * g1c**2) + 0.001 * g2**2
    m_hat, v_hat = m / (1 - 0.9**2), v / (1 - 0.999**2)
    np.testing.assert_allclose(upd["w"], -lr * (m_hat / (np.sqrt(v_hat) + eps) + wd), rtol=1e-4)


def test_training_steps_reduce_loss():
    optim = OptimConfig(learning_rate=3e-3, warmup_steps=1)
    state = init_train_state(jax.random.key(0), CFG, optim)
    np.testing.assert_allclose(state.log_temperature, math.log(0.1), rtol=1e-6)
    step = jax.jit(make_train_step(CFG, optim))
    batch = make_batch(8)
    before, _ = loss_fn(state.params, state.log_temperature, CFG, batch, None)
    keys = jax.random.split(jax.random.key(1), 25)
    for k in keys:
        state, aux = step(state, batch, k)
    after, _ = loss_fn(state.params, state.log_temperature, CFG, batch, None)
    assert np.isfinite(aux["loss"]) and int(state.step) == 25
    assert float(after) < float(before) - 0.1
    # per-dim entropy (~1.4) is above the target (-2): the temperature goes down
    assert float(state.log_temperature) < math.log(0.1)
    # same keys -> same bits
    state2 = init_train_state(jax.random.key(0), CFG, optim)
    for k in keys:
        state2, _ = step(state2, batch, k)
    assert all(jax.tree.leaves(jax.tree.map(np.array_equal, state.params, state2.params)))


def _close(a, b, rtol=2e-5, atol=1e-6):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


def test_micro_batches_sum_to_the_whole_batch(params):
    # Uneven padding: each slice has its own valid count, so slices averaged on their own
    # would not add up to the whole batch's loss; divided by the batch's counts they do.
    batch = make_batch(4, lengths=(K, K, 3, 1))
    grads_fn = jax.jit(batch_gradients, static_argnums=(2, 5))
    (loss, aux), grads = grads_fn(params, LOG_T, CFG, batch, None, 0)
    (loss2, aux2), grads2 = grads_fn(params, LOG_T, CFG, batch, None, 2)
    _close((loss, aux, grads), (loss2, aux2, grads2))
    halves = [{k: v[i:i + 2] for k, v in batch.items()} for i in (0, 2)]
    own = [float(loss_normalisers(h)["valid"]) for h in halves]
    assert own[0] != own[1]  # the slices' own averages would weigh steps unequally
    norms = loss_normalisers(batch)
    parts = [loss_fn(params, LOG_T, CFG, h, None, norms)[0] for h in halves]
    np.testing.assert_allclose(float(parts[0] + parts[1]), float(loss), rtol=1e-5)


def test_micro_batched_train_step_is_deterministic_and_learns():
    optim = OptimConfig(learning_rate=3e-3, warmup_steps=1)
    step = jax.jit(make_train_step(CFG, optim, micro_batch=2))
    batch = make_batch(8, lengths=(4, 2, 3, K))
    runs = []
    for _ in range(2):
        state = init_train_state(jax.random.key(0), CFG, optim)
        before, _ = loss_fn(state.params, state.log_temperature, CFG, batch, None)
        for k in jax.random.split(jax.random.key(1), 20):
            state, aux = step(state, batch, k)
        runs.append(state)
    after, _ = loss_fn(state.params, state.log_temperature, CFG, batch, None)
    assert float(after) < float(before) - 0.1
    np.testing.assert_allclose(aux["temperature"], np.exp(runs[0].log_temperature), rtol=0.01)
    assert all(jax.tree.leaves(jax.tree.map(np.array_equal, runs[0].params, runs[1].params)))


def test_micro_batch_splits_into_the_fewest_equal_passes():
    assert [micro_batches(2048, m) for m in (0, 256, 2048, 4096, 1000)] == [1, 8, 1, 1, 4]
    assert micro_batches(300, 256) == 2 and micro_batches(7, 2) == 7
    with pytest.raises(ValueError, match="micro_batch must be >= 0, got -1"):
        micro_batches(32, -1)
    with pytest.raises(ValueError, match=r"micro_batch must be an integer >= 0, got -2"):
        PretrainConfig(micro_batch=-2)
