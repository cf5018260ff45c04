"""The CDT rollout: left-padded context == unpadded prefix, target bookkeeping, determinism."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax import envs
from safecdt_jax.deploy.rollout import cdt_episode, evaluate_targets
from safecdt_jax.model import CDTConfig, apply_cdt, init_cdt

TASK = "PointCircle1"


@functools.cache
def _setup():
    env, params = envs.make(TASK)
    cfg = CDTConfig.preset("tiny", env.observation_size, env.action_size, env.episode_length)
    model = init_cdt(jax.random.PRNGKey(0), cfg)
    # A biased action head so the robot drives (and leaves the walls: costs to book-keep).
    model["action_mean"]["bias"] = jnp.array([1.0, 0.4])
    run = jax.jit(lambda k, r, c: cdt_episode(k, env, params, model, cfg, r, c))
    return env, params, cfg, model, run


def test_padded_context_equals_unpadded_prefix():
    _, _, cfg, model, run = _setup()
    ep = jax.device_get(run(jax.random.PRNGKey(3), 40.0, 5.0))
    k = cfg.seq_len
    for t in (0, 1, k - 2, k - 1, k, k + 5, 200):
        lo = max(0, t - k + 1)
        actions = ep["actions"][lo:t + 1].copy()
        actions[-1] = 0.0  # the current step's action slot is a dummy
        prefix = {
            "states": ep["observations"][lo:t + 1],
            "actions": actions,
            "returns_to_go": ep["returns_to_go"][lo:t + 1] * 0.1,
            "costs_to_go": ep["costs_to_go"][lo:t + 1],
            "timesteps": np.arange(lo, t + 1),
            "mask": np.ones(t + 1 - lo, np.float32),
        }
        out = apply_cdt(model, cfg, {n: jnp.asarray(v)[None] for n, v in prefix.items()})
        expected = np.clip(np.asarray(out["action_mean"][0, -1]), -1, 1)
        np.testing.assert_allclose(ep["actions"][t], expected, atol=1e-5, err_msg=f"step {t}")


def test_targets_decrement_by_realized_reward_and_cost():
    env, _, _, _, run = _setup()
    ep = jax.device_get(run(jax.random.PRNGKey(3), 40.0, 5.0))
    assert ep["costs"].sum() > 5  # the biased policy overruns the budget, so the clip matters
    rtg = ep["returns_to_go"]
    np.testing.assert_allclose(rtg[1:], rtg[:-1] - ep["rewards"][:-1], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(ep["costs_to_go"][1:],
                               np.maximum(ep["costs_to_go"][:-1] - ep["costs"][:-1], 0.0))
    assert ep["costs_to_go"].min() == 0.0
    assert int(ep["length"]) == env.episode_length
    assert ep["return"] == pytest.approx(ep["rewards"].sum())


def test_constant_targets_hold_all_episode():
    env, params, cfg, model, _ = _setup()
    const = cfg.replace(constant_targets=True)
    ep = jax.device_get(jax.jit(lambda k: cdt_episode(k, env, params, model, const, 40.0, 5.0))(
        jax.random.PRNGKey(3)))
    assert ep["costs"].sum() > 5 and ep["rewards"].sum() != 0  # a decrement would show
    np.testing.assert_array_equal(ep["returns_to_go"], 40.0)
    np.testing.assert_array_equal(ep["costs_to_go"], 5.0)


def test_constant_targets_exclude_token_rates():
    _, _, cfg, _, _ = _setup()
    with pytest.raises(ValueError, match="token_rates and constant_targets"):
        cfg.replace(constant_targets=True, token_rates=True)


def test_unclipped_ctg_goes_negative():
    env, params, cfg, model, _ = _setup()
    ep = jax.jit(lambda k: cdt_episode(k, env, params, model, cfg, 40.0, 5.0, clip_ctg=False))(
        jax.random.PRNGKey(3))
    ctg = np.asarray(ep["costs_to_go"])
    assert ctg.min() < 0
    np.testing.assert_allclose(ctg[-1], 5.0 - np.asarray(ep["costs"])[:-1].sum())


def test_runtime_budget_ends_the_episode_at_the_first_step_over_it():
    env, params, cfg, model, run = _setup()
    full = jax.device_get(run(jax.random.PRNGKey(3), 40.0, 5.0))
    stop = 4.0
    assert full["cost"] > stop + 1  # the biased policy overruns, so the wrapper must act
    cut = jax.device_get(jax.jit(lambda k: cdt_episode(
        k, env, params, model, cfg, 40.0, 5.0, stop_cost=stop))(jax.random.PRNGKey(3)))
    over = int(np.argmax(np.cumsum(full["costs"]) > stop))  # the step whose cost crosses B
    assert int(cut["length"]) == over + 1
    assert cut["cost"] == stop + 1  # 0/1 costs: a violating episode costs B + 1
    n = over + 1
    np.testing.assert_array_equal(cut["actions"][:n], full["actions"][:n])
    np.testing.assert_array_equal(cut["rewards"][n:], 0.0)
    assert cut["return"] == pytest.approx(full["rewards"][:n].sum(), abs=1e-4)


def test_same_key_same_bits_and_vmapped_targets_match_single_runs():
    _, params, cfg, model, run = _setup()
    env = envs.make(TASK)[0]
    a = jax.device_get(run(jax.random.PRNGKey(5), 20.0, 10.0))
    b = jax.device_get(run(jax.random.PRNGKey(5), 20.0, 10.0))
    for name in a:
        np.testing.assert_array_equal(a[name], b[name])
    # Over a short horizon: batched and single programs round differently, and those tiny
    # differences grow along a 500-step trajectory that hits walls.
    res = jax.jit(lambda k: evaluate_targets(k, env, params, model, cfg, jnp.array([20.0, 30.0]),
                                             jnp.array([10.0, 0.0]), 2, horizon=60))(
        jax.random.PRNGKey(7))
    assert res.costs.shape == (2, 2)
    keys = jax.random.split(jax.random.PRNGKey(7), 2)
    single = jax.device_get(jax.jit(
        lambda k: cdt_episode(k, env, params, model, cfg, 30.0, 0.0, horizon=60))(keys[1]))
    np.testing.assert_allclose(res.costs[1, 1], single["cost"])
    np.testing.assert_allclose(res.returns[1, 1], single["return"], rtol=1e-2)


def test_stochastic_actions_sample_the_head_with_the_step_keys():
    env, params, cfg, model, run = _setup()
    noisy = cfg.replace(stochastic_actions=True)
    go = jax.jit(lambda k: cdt_episode(k, env, params, model, noisy, 40.0, 5.0, horizon=50))
    a, b = jax.device_get(go(jax.random.PRNGKey(3))), jax.device_get(go(jax.random.PRNGKey(3)))
    np.testing.assert_array_equal(a["actions"], b["actions"])  # same key, same bits
    mean = jax.device_get(run(jax.random.PRNGKey(3), 40.0, 5.0))["actions"][:50]
    assert not np.allclose(a["actions"], mean)  # the samples are not the mean actions
    # With a vanishing std the sampled episode is the deterministic one.
    narrow = {**model, "action_log_std": {**model["action_log_std"],
                                          "bias": jnp.full((2,), -30.0)}}
    ep = jax.device_get(jax.jit(lambda k: cdt_episode(k, env, params, narrow, noisy, 40.0, 5.0,
                                                      horizon=50))(jax.random.PRNGKey(3)))
    np.testing.assert_allclose(ep["actions"], mean, atol=1e-5)


def test_cost_terms_count_each_terms_steps_and_change_nothing_else():
    env, params, cfg, model, _ = _setup()
    key = jax.random.PRNGKey(3)
    plain = jax.device_get(jax.jit(lambda k: cdt_episode(
        k, env, params, model, cfg, 40.0, 5.0, stop_cost=4.0))(key))
    terms = jax.device_get(jax.jit(lambda k: cdt_episode(
        k, env, params, model, cfg, 40.0, 5.0, stop_cost=4.0, cost_terms=True))(key))
    for name in plain:
        np.testing.assert_array_equal(terms[name], plain[name], err_msg=name)
    # the Circle task's one term is its whole cost, counted up to the cut at the budget
    assert list(terms["cost_terms"]) == list(env.task.cost_terms()) == ["cost_out_of_boundary"]
    assert terms["cost_terms"]["cost_out_of_boundary"] == plain["cost"] == 5.0
