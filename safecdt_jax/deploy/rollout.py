"""One CDT episode in an environment as a single `lax.scan` (pretraining evaluation and deployment).

The policy sees a window of the last K steps. Before step K-1 the window is left-padded: real
steps sit at its right end with `mask` 1 and padding at its left with `mask` 0, so the model's
causal, key-masked attention gives the same action as running it on the unpadded prefix
(`tests/test_deploy_rollout.py` checks this). After each step the targets are decremented by what
was realized: `rtg -= r_t`, `ctg -= c_t` (docs/METHOD.md section 1), in raw units; the model
reads the return-to-go times `cfg.reward_scale` and the cost-to-go times `cfg.cost_scale`, as in
pretraining (the encoding belongs to the model's config).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from safecdt_jax.envs.env import SafetyEnv
from safecdt_jax.envs.rollout import policy_episode
from safecdt_jax.envs.types import EnvParams
from safecdt_jax.model.cdt import Params, newest_action
from safecdt_jax.model.config import CDTConfig


class Context(NamedTuple):
    """The policy's sliding window of the last K steps, newest at index K-1.

    states [K, obs], actions [K, act], returns_to_go [K] and costs_to_go [K] (already scaled as
    the model reads them), timesteps [K] int32 (absolute step in the episode), mask [K] float32
    (1 = a real step, 0 = left padding).
    """

    states: jax.Array
    actions: jax.Array
    returns_to_go: jax.Array
    costs_to_go: jax.Array
    timesteps: jax.Array
    mask: jax.Array


def context_init(cfg: CDTConfig) -> Context:
    """An empty (all-padding) window of `cfg.seq_len` steps."""
    k = cfg.seq_len
    return Context(
        states=jnp.zeros((k, cfg.obs_dim), jnp.float32),
        actions=jnp.zeros((k, cfg.act_dim), jnp.float32),
        returns_to_go=jnp.zeros((k,), jnp.float32),
        costs_to_go=jnp.zeros((k,), jnp.float32),
        timesteps=jnp.zeros((k,), jnp.int32),
        mask=jnp.zeros((k,), jnp.float32),
    )


def context_push(ctx: Context, obs, rtg, ctg, t) -> Context:
    """Shift the window left by one and append step `t` (its action slot 0 until it is chosen)."""

    def push(x, new):
        return jnp.concatenate([x[1:], jnp.asarray(new, x.dtype)[None]], axis=0)

    return Context(
        states=push(ctx.states, obs),
        actions=push(ctx.actions, jnp.zeros_like(ctx.actions[0])),
        returns_to_go=push(ctx.returns_to_go, rtg),
        costs_to_go=push(ctx.costs_to_go, ctg),
        timesteps=push(ctx.timesteps, t),
        mask=push(ctx.mask, 1.0),
    )


def context_action(params: Params, cfg: CDTConfig, ctx: Context,
                   key: jax.Array | None = None) -> jax.Array:
    """Action [act] for the newest step: the policy mean clipped to the box, or with
    `cfg.stochastic_actions` a sample of the policy drawn with `key`.

    Uses the trimmed evaluation pass (`model.cdt.newest_action`), equal to `last_action`.
    """
    batch = {name: value[None] for name, value in ctx._asdict().items()}
    return newest_action(params, cfg, batch, key)[0]


def cdt_episode(
    key: jax.Array,
    env: SafetyEnv,
    env_params: EnvParams,
    params: Params,
    cfg: CDTConfig,
    target_return,
    target_cost,
    *,
    clip_ctg: bool = True,
    horizon: int | None = None,
    stop_cost=None,
    cost_terms: bool = False,
) -> dict[str, jax.Array]:
    """Run one episode of the CDT with the given targets, T steps (default: the env's horizon).

    Args:
        key: PRNG key of the episode (layout and goal re-sampling).
        env, env_params: the task and its level/dynamics data.
        params: CDT parameters (base, or base merged with LoRA adapters).
        cfg: the model's config (static), token encoding included.
        target_return: initial return-to-go, raw return units (traced scalar ok).
        target_cost: initial cost-to-go, raw cost units = cost steps (traced scalar ok).
        clip_ctg: clip the cost-to-go at 0 once the budget is spent (default, docs/METHOD.md
            section 1); False keeps OSRL's rule of letting it go negative. Neither applies
            with `cfg.constant_targets`, whose tokens keep the targets all episode.
        horizon: steps T to run (static); None = the env's time limit. A shorter horizon cuts
            the episode there (for tests and quick looks).
        stop_cost: the runtime budget (cost units; traced scalar ok): the episode ends after
            the step at which its cost first exceeds it, as the paper's budget wrapper ends it
            (so a violating episode costs B + 1 with 0/1 costs). None: never stopped for cost.
        cost_terms: also return `cost_terms`, the episode's cost steps per term of the task
            (static; `policy_episode`).

    Returns a dict: per step `observations [T, obs]` (the observation the action was chosen
    from), `actions [T, act]`, `rewards [T]`, `costs [T]`, `returns_to_go [T]`, `costs_to_go [T]`
    (raw targets the model saw at each step); per episode `length` (int32 steps until done),
    `return` and `cost` (sums over the episode). Steps after `done` are zero and not counted.
    """
    def act(carry, obs, t, step_key):
        ctx, rtg, ctg = carry
        ctx = context_push(ctx, obs, rtg * cfg.reward_scale, ctg * cfg.cost_scale, t)
        # The step key also reaches nothing else: the env's own noise comes from its state.
        action = context_action(params, cfg, ctx, step_key)
        return action, (ctx._replace(actions=ctx.actions.at[-1].set(action)), rtg, ctg)

    def observe(carry, reward, cost):
        if cfg.constant_targets:  # the tokens name the episode's targets; nothing is spent
            return carry
        ctx, rtg, ctg = carry
        new_ctg = jnp.maximum(ctg - cost, 0.0) if clip_ctg else ctg - cost
        return ctx, rtg - reward, new_ctg

    out = policy_episode(
        env, env_params, key, act, observe,
        (context_init(cfg), jnp.float32(target_return), jnp.float32(target_cost)),
        record=lambda carry: {"returns_to_go": carry[1], "costs_to_go": carry[2]},
        horizon=horizon, stop_cost=stop_cost, cost_terms=cost_terms)
    out.pop("alive")
    return out


class EvalResult(NamedTuple):
    """Per (target, episode) totals of `evaluate_targets`: arrays [n_targets, n_episodes]."""

    returns: jax.Array
    costs: jax.Array


def evaluate_targets(
    key: jax.Array,
    env: SafetyEnv,
    env_params: EnvParams,
    params: Params,
    cfg: CDTConfig,
    target_returns,
    target_costs,
    episodes: int,
    **rollout_kwargs,
) -> EvalResult:
    """Episode return and cost for every (target, episode): one vmapped program, not jitted here.

    `target_returns`, `target_costs`: [n_targets] raw targets; the same `episodes` keys (layouts)
    are used for every target, so targets are compared on equal layouts.
    """
    keys = jax.random.split(key, episodes)

    def one(k, r, c):
        ep = cdt_episode(k, env, env_params, params, cfg, r, c, **rollout_kwargs)
        return ep["return"], ep["cost"]

    per_target = jax.vmap(jax.vmap(one, (0, None, None)), (None, 0, 0))
    returns, costs = per_target(keys, jnp.asarray(target_returns, jnp.float32),
                                jnp.asarray(target_costs, jnp.float32))
    return EvalResult(returns, costs)
