"""Our tasks as Brax envs: the adapter's API, Brax's auto-reset over it, Brax's own PPO on it."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training as brax_wrappers

from safecdt_jax.envs.brax_env import BraxSafetyEnv


def test_adapter_steps_like_our_env_and_reports_cost():
    from safecdt_jax import envs
    env = BraxSafetyEnv("PointGoal1")
    ours, params = envs.make("PointGoal1")
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    assert state.obs.shape == (env.observation_size,) == (60,) and env.action_size == 2
    assert set(state.metrics) >= {"cost", "goal_met", "cost_hazards"}
    a = jnp.array([0.7, -0.3])
    nxt = jax.jit(env.step)(state, a)
    ref = jax.jit(lambda k: ours.step(ours.reset(k, params), a, params))(jax.random.PRNGKey(0))
    np.testing.assert_allclose(nxt.obs, ref.obs, rtol=1e-5, atol=1e-6)
    assert float(nxt.reward) == float(ref.reward) and float(nxt.metrics["cost"]) == float(ref.cost)


def test_dynamics_overrides_are_params_and_bad_fields_are_named():
    env = BraxSafetyEnv("CarGoal2", friction_scale=0.5)
    assert float(env._params.friction_scale) == 0.5
    with pytest.raises(ValueError, match=r"unknown EnvParams field.*frction_scale"):
        BraxSafetyEnv("CarGoal2", frction_scale=0.5)


def test_brax_auto_reset_resets_exactly_the_finished_envs():
    env = brax_wrappers.wrap(BraxSafetyEnv("PointCircle1"), episode_length=5)
    state = jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(1), 3))
    step = jax.jit(env.step)
    for _ in range(2):
        state = step(state, jnp.ones((3, 2)))
    # env 1 is on its last step; envs 0 and 2 are mid-episode
    state = state.replace(info={**state.info, "steps": jnp.array([2.0, 4.0, 2.0])})
    before = state.obs
    state = step(state, jnp.ones((3, 2)))
    np.testing.assert_array_equal(state.done, [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(state.obs[1], state.info["first_obs"][1])  # reset
    for i in (0, 2):
        assert not np.array_equal(state.obs[i], state.info["first_obs"][i])
        assert not np.array_equal(state.obs[i], before[i])  # and stepped on


def test_brax_ppo_trains_on_our_task():
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    factory = functools.partial(ppo_networks.make_ppo_networks,
                                policy_hidden_layer_sizes=(8,), value_hidden_layer_sizes=(8,))
    curve = []
    _, _, metrics = ppo.train(
        BraxSafetyEnv("PointCircle1"), num_timesteps=1600, episode_length=20, num_envs=4,
        batch_size=4, num_minibatches=2, unroll_length=10, num_updates_per_batch=1,
        num_evals=2, network_factory=factory, seed=0,
        progress_fn=lambda step, m: curve.append((step, m)))
    assert curve and curve[-1][0] >= 1600
    assert np.isfinite(float(metrics["eval/episode_reward"]))
    assert "eval/episode_cost" in metrics  # our cost, summed per episode by Brax's wrappers
