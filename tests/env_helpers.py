"""Compiled env programs shared by the env tests (each is compiled once per test session)."""

import functools

import jax
import jax.numpy as jnp

from safecdt_jax import envs
from safecdt_jax.envs.rollout import run_episode


@functools.cache
def batch_episodes(name: str, length: int):
    """jit(vmap) of `length`-step random-policy episodes for task `name`: keys -> totals.

    The params are an argument, so level 1 and level 2 of a task share this program.
    """
    env, _ = envs.make(name)
    return jax.jit(jax.vmap(lambda k, p: run_episode(env, p, k, length=length), (0, None)))


@functools.cache
def jitted(name: str):
    """(reset, step) of task `name`, jitted."""
    env, _ = envs.make(name)
    return jax.jit(env.reset), jax.jit(env.step)


def hold(name: str, action, seconds: float, params=None, key=0):
    """State after holding a constant action for `seconds` from a reset with seed `key`."""
    env, default = envs.make(name)
    params = default if params is None else params
    reset, step = jitted(name)
    state = reset(jax.random.PRNGKey(key), params)
    for _ in range(round(seconds / env.dt)):
        state = step(state, jnp.asarray(action, jnp.float32), params)
    return state
