"""Whole-episode rollouts as one `lax.scan`, for demos, benchmarks and tests."""

from collections.abc import Callable
from typing import Any

import jax

from safecdt_jax.envs.env import SafetyEnv
from safecdt_jax.envs.types import EnvParams, State

Policy = Callable[[jax.Array, State], jax.Array]  # (key, state) -> action [2]


def uniform_policy(key: jax.Array, state: State) -> jax.Array:
    """Uniform random actions in [-1, 1]^2 (the reference's random-policy statistics)."""
    return jax.random.uniform(key, (2,), minval=-1.0, maxval=1.0)


def scan_episode(env: SafetyEnv, params: EnvParams, key: jax.Array, policy: Policy,
                 record: Callable[[State], Any], length: int | None = None) -> tuple[State, Any]:
    """Resets, then `length` steps (default: the task's time limit) of `policy` as one scan.

    `policy(key, state)` sees the state before each step (`state.info["steps"]` is the step
    index, for scripted actions); `record(state)` picks what to keep from the state after each
    step. Returns (final state, records stacked over steps).
    """
    length = env.episode_length if length is None else length
    k_reset, k_act = jax.random.split(key)

    def body(state, k):
        state = env.step(state, policy(k, state), params)
        return state, record(state)

    return jax.lax.scan(body, env.reset(k_reset, params), jax.random.split(k_act, length))


def run_episode(env: SafetyEnv, params: EnvParams, key: jax.Array,
                policy: Policy = uniform_policy, length: int | None = None) -> dict:
    """Resets and runs one episode of `length` steps (default: the task's time limit).

    Returns per-episode totals: `return` (sum of rewards), `cost` (number of cost steps),
    `goals` (goals reached), and `nonfinite_actions`.
    """
    state, (r, c, g) = scan_episode(
        env, params, key, policy, lambda s: (s.reward, s.cost, s.info["goal_met"]), length)
    return {"return": r.sum(), "cost": c.sum(), "goals": g.sum(),
            "nonfinite_actions": state.info["nonfinite_actions"]}


def random_episode(env: SafetyEnv, params: EnvParams, key: jax.Array) -> dict:
    """One full episode under the uniform random policy (see `run_episode`)."""
    return run_episode(env, params, key, uniform_policy)


__all__ = ["random_episode", "run_episode", "scan_episode", "uniform_policy"]
