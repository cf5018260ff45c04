"""The env contract: names, sizes, purity (same key, jit, vmap), params as data, bad actions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from env_helpers import jitted

from safecdt_jax import envs

SIZES = {"CarGoal": 72, "PointGoal": 60, "CarCircle": 40, "PointCircle": 28}


def test_unknown_name_lists_valid_names():
    with pytest.raises(ValueError, match=r"unknown task 'CarGoal3'.*PointCircle2"):
        envs.make("CarGoal3")


@pytest.mark.parametrize("name", envs.NAMES)
def test_sizes_and_levels_share_one_env(name):
    env, params = envs.make(name)
    assert env.observation_size == SIZES[name[:-1]]
    assert env.action_size == 2
    assert env.episode_length == (1000 if "Goal" in name else 500)
    other, other_params = envs.make(name[:-1] + ("2" if name.endswith("1") else "1"))
    assert other is env  # one compiled program serves both levels
    assert jax.tree.structure(other_params) == jax.tree.structure(params)


@pytest.mark.parametrize("name", ["CarGoal2", "PointCircle1"])
def test_reset_observation_at_rest(name):
    env, params = envs.make(name)
    reset, _ = jitted(name)
    state = reset(jax.random.PRNGKey(0), params)
    assert state.obs.shape == (env.observation_size,)
    np.testing.assert_allclose(state.obs[:3], [0.0, 0.0, 9.81], atol=1e-5)  # accelerometer
    np.testing.assert_allclose(state.obs[3:9], 0.0, atol=1e-6)  # velocimeter, gyro
    assert float(state.cost) == 0.0 and float(state.done) == 0.0


def _run(step, state, params, actions):
    for a in actions:
        state = step(state, a, params)
    return state


def test_same_key_same_bits_and_jit_equals_nojit():
    env, params = envs.make("PointGoal2")
    reset, step = jitted("PointGoal2")
    actions = jax.random.uniform(jax.random.PRNGKey(3), (4, 2), minval=-1, maxval=1)
    a = _run(step, reset(jax.random.PRNGKey(7), params), params, actions)
    b = _run(step, reset(jax.random.PRNGKey(7), params), params, actions)
    jax.tree.map(lambda x, y: np.testing.assert_array_equal(x, y), a, b)
    # one step op by op (eager MJX is slow) from the same state equals the compiled step
    with jax.disable_jit():
        c = env.step(a, actions[0], params)
    d = step(a, actions[0], params)
    np.testing.assert_allclose(c.obs, d.obs, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(c.reward, d.reward, rtol=1e-4, atol=1e-6)
    assert float(c.cost) == float(d.cost)


def test_vmap_equals_single_runs():
    env, params = envs.make("CarCircle2")
    reset, step = jitted("CarCircle2")
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (3, 4, 2), minval=-1, maxval=1)
    vreset, vstep = jax.jit(jax.vmap(env.reset, (0, None))), jax.jit(
        jax.vmap(env.step, (0, 0, None)))
    batch = _run(vstep, vreset(keys, params), params, actions)
    for i in range(4):
        single = _run(step, reset(keys[i], params), params, actions[:, i])
        np.testing.assert_allclose(batch.obs[i], single.obs, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(batch.data.qpos[i], single.data.qpos, rtol=1e-5, atol=1e-6)


def test_switching_level_and_dynamics_does_not_recompile():
    env, p1 = envs.make("PointGoal1")
    _, p2 = envs.make("PointGoal2")
    traces = []

    @jax.jit
    def step(state, action, params):
        traces.append(1)  # runs only while tracing
        return env.step(state, action, params)

    reset, _ = jitted("PointGoal1")
    s = reset(jax.random.PRNGKey(0), p1)
    for params in (p1, p2, p1.replace(friction_scale=jnp.float32(0.5)),
                   p2.replace(mass_scale=jnp.float32(2.0))):
        s = step(s, jnp.ones(2), params)
    assert len(traces) == 1


def test_nonfinite_action_is_zero_and_counted():
    _env, params = envs.make("PointGoal1")
    reset, step = jitted("PointGoal1")
    s0 = reset(jax.random.PRNGKey(0), params)
    bad = step(s0, jnp.array([jnp.nan, jnp.inf]), params)
    zero = step(s0, jnp.zeros(2), params)
    np.testing.assert_array_equal(bad.obs, zero.obs)
    assert np.isfinite(np.asarray(bad.data.qpos)).all()
    assert int(bad.info["nonfinite_actions"]) == 1 and int(zero.info["nonfinite_actions"]) == 0
    bad2 = step(bad, jnp.array([1.0, jnp.nan]), params)
    assert int(bad2.info["nonfinite_actions"]) == 2


def test_episode_ends_at_time_limit():
    env, params = envs.make("PointCircle1")
    reset, step = jitted("PointCircle1")
    s = reset(jax.random.PRNGKey(0), params)
    s = s.replace(info={**s.info, "steps": jnp.int32(env.episode_length - 2)})
    s = step(s, jnp.zeros(2), params)
    assert float(s.done) == 0.0
    s = step(s, jnp.zeros(2), params)
    assert float(s.done) == 1.0 and int(s.info["steps"]) == env.episode_length


def test_import_prints_nothing():
    """MJX's probe for its optional Warp backend prints two lines when Warp is absent; importing
    the envs must not show them (a user's first screen is the project's own output)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "from safecdt_jax import envs"],
                         capture_output=True, text=True, check=True)
    assert "warp" not in out.stdout.lower() and out.stdout == ""
