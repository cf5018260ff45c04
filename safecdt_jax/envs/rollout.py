"""Whole-episode rollouts as one `lax.scan`, for demos, benchmarks and tests."""

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

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


def policy_episode(env: SafetyEnv, params: EnvParams, key: jax.Array, act: Callable,
                   observe: Callable, policy_state: Any, *, record: Callable | None = None,
                   horizon: int | None = None, stop_cost=None, cost_terms: bool = False
                   ) -> dict:
    """One episode of a stateful policy, the protocol every evaluated policy shares (the CDT's
    deployment, the offline baselines): one scan of `horizon` steps (default: the time limit)
    with an alive mask, optionally cut by the paper's runtime budget.

    Each step: `act(policy_state, obs, t, key) -> (action, policy_state)`, the env steps, then
    `observe(policy_state, reward, cost) -> policy_state` sees what was realized (both 0 once
    the episode is over). The reset uses `key` itself; step t's key is `fold_in(key, t + 1)`.
    `stop_cost` (cost units, traced ok): the episode ends after the step at which its cost
    first exceeds it; None never stops for cost.

    Returns per step `observations [T, obs]` (what the action was chosen from), `actions`,
    `rewards`, `costs`, `alive` and whatever `record(policy_state)` (read before `observe`)
    adds; observations, actions, rewards and costs are 0 after the end (recorded fields are
    not masked). Per episode `length` (int32 steps), `return` and `cost` (sums), and with
    `cost_terms` (static) `cost_terms`: per term of the task (`task.cost_terms()`, e.g.
    `cost_hazards`), the steps of the episode at which that term cost (terms overlap: a step
    in a hazard touching a vase counts in both, and once in `cost`).
    """
    horizon = env.episode_length if horizon is None else horizon
    stop = jnp.float32(jnp.inf if stop_cost is None else stop_cost)

    def body(carry, t):
        state, pstate, spent, alive = carry
        action, pstate = act(pstate, state.obs, t, jax.random.fold_in(key, t + 1))
        nxt = env.step(state, action, params)
        reward = jnp.where(alive, nxt.reward, 0.0)
        cost = jnp.where(alive, nxt.cost, 0.0)
        out = {"observations": state.obs, "actions": action, "rewards": reward, "costs": cost,
               "alive": alive, **(record(pstate) if record is not None else {})}
        if cost_terms:
            out["cost_terms"] = {k: jnp.where(alive & (nxt.info[k] > 0), 1.0, 0.0)
                                 for k in env.task.cost_terms()}
        spent = spent + cost
        alive_next = alive & (nxt.done < 0.5) & (spent <= stop)
        return (nxt, observe(pstate, reward, cost), spent, alive_next), out

    carry = (env.reset(key, params), policy_state, jnp.float32(0.0), jnp.bool_(True))
    _, out = jax.lax.scan(body, carry, jnp.arange(horizon, dtype=jnp.int32))
    alive = out["alive"]
    out["observations"] = jnp.where(alive[:, None], out["observations"], 0.0)
    out["actions"] = jnp.where(alive[:, None], out["actions"], 0.0)
    out["length"] = alive.sum().astype(jnp.int32)
    out["return"] = out["rewards"].sum()
    out["cost"] = out["costs"].sum()
    if cost_terms:
        out["cost_terms"] = {k: v.sum() for k, v in out["cost_terms"].items()}
    return out


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


__all__ = ["policy_episode", "random_episode", "run_episode", "scan_episode", "uniform_policy"]
