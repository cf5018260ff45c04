"""The cost-prioritised adaptive target scheduler (docs/METHOD.md section 2).

Every U episodes the scheduler looks at the last W finished episodes and moves the cost ratio CR
(CTG target = CR * B) by a momentum step driven by the Wilson lower bound A_C of "episode cost
<= B"; the return ratio RR (RTG target = RR * R_ref) moves only when A_C > 0.9, driven by A_R.

All functions are pure and shape-static: the window is a fixed-size array with a validity mask,
and the variant (scheduler on/off, fixed ratios) is selected with `jnp.where`, so one compiled
program serves every variant and vmaps over a stack of them. Call order in the deployment loop,
after episode `e` (0-based) finished: `scheduler_step` (updates at stage ends), then
`stage_ratios(state, e + 1, ...)` for the next episode's targets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp

from safecdt_jax.deploy.config import DeployConfig, Variant


@dataclass(frozen=True)
class SchedulerState:
    """The scheduler's carry (a pytree of scalars).

    cr, rr: float32, the current cost and return ratios (used for the current stage).
    momentum: float32, the momentum d >= 1 of the cost-ratio step.
    last_dir: int32, the last non-zero direction of CR (-1 tighten, +1 relax; 0 before any move).
    a_c, a_r: float32, the Wilson lower bounds of the last applied update (0 before any).
    """

    cr: Any
    rr: Any
    momentum: Any
    last_dir: Any
    a_c: Any
    a_r: Any


jax.tree_util.register_dataclass(SchedulerState)


def scheduler_init(cfg: DeployConfig) -> SchedulerState:
    """The state at deployment start: CR_0, RR_0, momentum 1, no previous direction."""
    return SchedulerState(
        cr=jnp.asarray(cfg.cr0, jnp.float32),
        rr=jnp.asarray(cfg.rr0, jnp.float32),
        momentum=jnp.ones((), jnp.float32),
        last_dir=jnp.zeros((), jnp.int32),
        a_c=jnp.zeros((), jnp.float32),
        a_r=jnp.zeros((), jnp.float32),
    )


def wilson_lower(k, n, z: float):
    """Lower end of the Wilson score interval for k successes out of n trials (float32).

    `(p + z^2/2n - z sqrt(p(1-p)/n + z^2/4n^2)) / (1 + z^2/n)` with p = k/n; broadcasts over
    arrays. n = 0 gives 0 by definition: no evidence, the most conservative lower bound.
    """
    k = jnp.asarray(k, jnp.float32)
    n = jnp.asarray(n, jnp.float32)
    safe_n = jnp.maximum(n, 1.0)  # keeps the n = 0 branch finite, so gradients/where are clean
    p = k / safe_n
    z2 = z * z
    radius = z * jnp.sqrt(jnp.maximum(p * (1.0 - p) / safe_n + z2 / (4.0 * safe_n**2), 0.0))
    lower = (p + z2 / (2.0 * safe_n) - radius) / (1.0 + z2 / safe_n)
    return jnp.where(n > 0, lower, 0.0)


def window_mask(episode_index, size: int, window: int):
    """Bool [size]: which slots of a per-episode history array form the scheduler window.

    For history arrays indexed by episode number (slot i = episode i, length `size` >= E),
    selects the last `window` finished episodes up to and including `episode_index`
    (fewer at the start; none when `episode_index` < 0).
    """
    i = jnp.arange(size)
    return (i <= episode_index) & (i > episode_index - window)


def scheduler_update(
    state: SchedulerState,
    window_costs,
    window_returns,
    window_rtg_targets,
    window_valid,
    budget,
    cfg: DeployConfig,
) -> tuple[SchedulerState, jax.Array, jax.Array]:
    """One stage update of CR and RR from the window (docs/METHOD.md section 2), unconditionally.

    Args:
        state: the current scheduler state.
        window_costs, window_returns: [W'] episode total cost and return, raw units.
        window_rtg_targets: [W'] the raw RTG target each episode was run with (its stage's).
        window_valid: [W'] bool, which entries are finished episodes of the window.
        budget: the cost budget B (raw cost units; traced scalar ok).
        cfg: the deployment config (static).

    Returns `(new_state, a_c, a_r)`: A_C = wilson_lower(#{cost <= B}, n, z), A_R =
    wilson_lower(#{return >= RTG target}, n, z); CR moves by dir * cr_step * d with dir = -1 if
    A_C < tighten_below, +1 if A_C > relax_above, else 0, and d = min(factor * d, d_max) when
    dir equals the last non-zero direction, else 1 (also on a hold); CR is clipped to
    [cr_min, cr_max]. RR moves by +-rr_step (A_R > relax_above / < tighten_below), clipped to
    [rr_min, rr_max], only when A_C > relax_above. An empty window (n = 0) moves nothing.
    """
    valid = jnp.asarray(window_valid, jnp.bool_)
    n = valid.sum()
    k_c = (valid & (jnp.asarray(window_costs) <= budget)).sum()
    k_r = (valid & (jnp.asarray(window_returns) >= jnp.asarray(window_rtg_targets))).sum()
    a_c = wilson_lower(k_c, n, cfg.z)
    a_r = wilson_lower(k_r, n, cfg.z)

    direction = _direction(a_c, cfg)
    direction = jnp.where(n > 0, direction, 0)  # no evidence: hold rather than tighten on A_C=0
    repeat = (direction != 0) & (direction == state.last_dir)
    momentum = jnp.where(
        repeat, jnp.minimum(cfg.momentum_factor * state.momentum, cfg.momentum_max), 1.0
    ).astype(jnp.float32)
    cr = jnp.clip(state.cr + direction * cfg.cr_step * momentum, cfg.cr_min, cfg.cr_max)

    # Cost-prioritised: reward-seeking only while the cost target is comfortably achievable.
    rr_dir = jnp.where(a_c > cfg.relax_above, _direction(a_r, cfg), 0)
    rr = jnp.clip(state.rr + rr_dir * cfg.rr_step, cfg.rr_min, cfg.rr_max)

    new = SchedulerState(
        cr=cr.astype(jnp.float32),
        rr=rr.astype(jnp.float32),
        momentum=momentum,
        last_dir=jnp.where(direction != 0, direction, state.last_dir).astype(jnp.int32),
        a_c=a_c,
        a_r=a_r,
    )
    return new, a_c, a_r


def _direction(a, cfg: DeployConfig):
    """-1 below `tighten_below`, +1 above `relax_above`, else 0 (int32)."""
    return jnp.where(a < cfg.tighten_below, -1, jnp.where(a > cfg.relax_above, 1, 0)).astype(
        jnp.int32
    )


def scheduler_step(
    state: SchedulerState,
    episode_index,
    window_costs,
    window_returns,
    window_rtg_targets,
    window_valid,
    budget,
    variant: Variant,
    cfg: DeployConfig,
) -> tuple[SchedulerState, jax.Array, jax.Array]:
    """`scheduler_update` gated for the loop: call after EVERY episode, it updates at stage ends.

    `episode_index` (0-based, traced ok) is the episode that just finished; the update applies
    when `(episode_index + 1) % stage_len == 0` and `variant.scheduler` is on, so stage k >= 1
    (episodes kU .. kU+U-1) runs with the ratios computed from the episodes before it. A_C and A_R
    are returned every call (for the per-episode metrics) whether or not the state changed.
    """
    new, a_c, a_r = scheduler_update(
        state, window_costs, window_returns, window_rtg_targets, window_valid, budget, cfg
    )
    apply = ((episode_index + 1) % cfg.stage_len == 0) & jnp.asarray(variant.scheduler)
    state = jax.tree.map(lambda a, b: jnp.where(apply, a, b), new, state)
    return state, a_c, a_r


def stage_ratios(state: SchedulerState, episode_index, variant: Variant, cfg: DeployConfig):
    """The (CR, RR) that episode `episode_index` is conditioned on, for any variant.

    Scheduler on: the scheduler's current ratios. Scheduler off: CR = `variant.cr_first` before
    `variant.switch_episode` and `variant.cr_second` from it on, RR = `cfg.rr0` throughout.
    The variant is data, so this lives beside the scheduler rather than in Python control flow.
    """
    fixed_cr = jnp.where(episode_index < variant.switch_episode, variant.cr_first,
                         variant.cr_second)
    cr = jnp.where(variant.scheduler, state.cr, fixed_cr)
    rr = jnp.where(variant.scheduler, state.rr, jnp.float32(cfg.rr0))
    return cr.astype(jnp.float32), rr.astype(jnp.float32)


def targets(cr, rr, budget, reference_return):
    """Raw-unit targets `(ctg, rtg) = (CR * B, RR * R_ref)` for the rollout's initial tokens.

    `budget` B in cost units, `reference_return` R_ref (95th percentile of the source data set's
    episode returns) in return units; the rollout applies the model's token scales itself.
    """
    ctg = jnp.asarray(cr, jnp.float32) * budget
    rtg = jnp.asarray(rr, jnp.float32) * reference_return
    return ctg, rtg
