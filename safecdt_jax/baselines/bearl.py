"""BEAR-Lagrangian (OSRL's `BEARL`): a squashed-Gaussian actor kept within the support of the
behaviour actions by an MMD constraint against VAE samples (a hand-updated dual alpha), reward
and cost double-ensemble critics, and a PID Lagrangian on the per-step cost value.

Each step: VAE -> reward critic -> cost critic -> actor and alpha -> soft target updates.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from safecdt_jax.baselines.common import (
    Algorithm,
    TrainState,
    Transitions,
    adam_step,
    double_q,
    init_networks,
    mmd_gaussian,
    pid_step,
    repeat,
    soft_update_targets,
    update_double_critics,
    update_vae,
)
from safecdt_jax.baselines.config import BaselineConfig
from safecdt_jax.baselines.networks import (
    VAE,
    QEnsemble,
    SquashedGaussian,
    squashed_sample,
)


def make(cfg: BaselineConfig, obs_dim: int, act_dim: int, qc_thres: float) -> Algorithm:
    """BEARL for observations of `obs_dim`, actions of `act_dim`, per-step cost threshold
    `qc_thres` (`common.qc_threshold`)."""
    actor = SquashedGaussian(cfg.hidden, act_dim)
    critic = QEnsemble(cfg.hidden, 2 * cfg.num_q)
    vae = VAE(cfg.vae_hidden, act_dim)
    n = cfg.next_actions

    def init(key: jax.Array) -> TrainState:
        return init_networks(key, cfg, actor, critic, vae, obs_dim, act_dim, False)

    def update(state: TrainState, batch: Transitions, key: jax.Array):
        k_vae, k_next, k_dec, k_pi = jax.random.split(key, 4)
        state, vae_loss = update_vae(state, vae, batch, k_vae, cfg.vae_lr, cfg.vae_beta)

        next_obs = repeat(batch.next_obs, n)
        next_act, _, _ = squashed_sample(k_next, *actor.apply(state.target["actor"], next_obs))
        state, q_loss, qc_loss = update_double_critics(state, critic, batch, next_obs, next_act,
                                                       cfg)

        obs_n = repeat(batch.obs, n)
        behaviour_raw = jax.lax.stop_gradient(
            vae.apply(state.params["vae"], k_dec, obs_n, True, method=VAE.sample))
        alpha = jnp.exp(state.log_alpha)

        def actor_loss(actor_params):
            act, raw, _ = squashed_sample(k_pi, *actor.apply(actor_params, obs_n))
            mmd = mmd_gaussian(behaviour_raw, raw, cfg.mmd_sigma)
            a0 = act[:, 0]  # the values are read at the first actor sample, as OSRL does
            q = double_q(critic, state.params["critic"], batch.obs, a0, cfg.num_q)
            qc = double_q(critic, state.params["cost_critic"], batch.obs, a0, cfg.num_q)
            pid = pid_step(state.pid, qc, qc_thres, cfg.pid)
            loss = (jnp.mean(-q + alpha * (mmd - cfg.mmd_threshold))
                    + jnp.mean(pid.lam * (qc - qc_thres)))
            return loss, (pid, mmd.mean(), qc.mean())

        state, pi_loss, (pid, mmd, qc_pi) = adam_step(state, "actor", actor_loss, cfg.actor_lr)
        log_alpha = jnp.clip(state.log_alpha + cfg.alpha_lr * alpha * (mmd - cfg.mmd_threshold),
                             -5.0, 5.0)
        state = state._replace(target=soft_update_targets(state, cfg.tau), pid=pid,
                               log_alpha=log_alpha, step=state.step + 1)
        return state, {"vae_loss": vae_loss, "critic_loss": q_loss, "cost_critic_loss": qc_loss,
                       "actor_loss": pi_loss, "qc": qc_pi, "lambda": pid.lam, "mmd": mmd,
                       "alpha": jnp.exp(log_alpha)}

    def act(params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        return jnp.tanh(actor.apply(params["actor"], obs)[0])

    return Algorithm(init, update, act)


__all__ = ["make"]
