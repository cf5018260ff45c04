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
    init_state,
    max_soft_clipped,
    mmd_gaussian,
    pid_step,
    regress_critic,
    repeat,
    soft_update,
    update_vae,
)
from safecdt_jax.baselines.config import BaselineConfig
from safecdt_jax.baselines.networks import (
    VAE,
    QEnsemble,
    SquashedGaussian,
    double_min,
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
        k_a, k_q, k_c, k_v, k_s = jax.random.split(key, 5)
        obs, act = jnp.zeros((1, obs_dim)), jnp.zeros((1, act_dim))
        params = {"actor": actor.init(k_a, obs), "critic": critic.init(k_q, obs, act),
                  "cost_critic": critic.init(k_c, obs, act),
                  "vae": vae.init(k_v, k_s, obs, act)}
        lrs = {"actor": cfg.actor_lr, "critic": cfg.critic_lr, "cost_critic": cfg.critic_lr,
               "vae": cfg.vae_lr}
        return init_state(params, lrs, ("actor", "critic", "cost_critic"))

    def update(state: TrainState, batch: Transitions, key: jax.Array):
        k_vae, k_next, k_dec, k_pi = jax.random.split(key, 4)
        state, vae_loss = update_vae(state, vae, batch, k_vae, cfg.vae_lr, cfg.vae_beta)

        next_obs = repeat(batch.next_obs, n)
        next_act, _, _ = squashed_sample(k_next, *actor.apply(state.target["actor"], next_obs))
        q_next = max_soft_clipped(critic.apply(state.target["critic"], next_obs, next_act),
                                  cfg.num_q, cfg.lmbda)
        y = cfg.reward_scale * batch.reward + cfg.gamma * (1.0 - batch.done) * q_next
        state, q_loss = regress_critic(state, "critic", critic, batch, y, cfg.critic_lr)
        qc_next = max_soft_clipped(critic.apply(state.target["cost_critic"], next_obs, next_act),
                                   cfg.num_q, cfg.lmbda)
        yc = cfg.cost_scale * batch.cost + cfg.gamma * qc_next  # no done mask, as OSRL
        state, qc_loss = regress_critic(state, "cost_critic", critic, batch, yc, cfg.critic_lr)

        obs_n = repeat(batch.obs, n)
        behaviour_raw = jax.lax.stop_gradient(
            vae.apply(state.params["vae"], k_dec, obs_n, True, method=VAE.sample))
        alpha = jnp.exp(state.log_alpha)

        def actor_loss(actor_params):
            act, raw, _ = squashed_sample(k_pi, *actor.apply(actor_params, obs_n))
            mmd = mmd_gaussian(behaviour_raw, raw, cfg.mmd_sigma)
            a0 = act[:, 0]  # the values are read at the first actor sample, as OSRL does
            q = jnp.minimum(*double_min(critic.apply(state.params["critic"], batch.obs, a0),
                                        cfg.num_q))
            qc = jnp.minimum(*double_min(
                critic.apply(state.params["cost_critic"], batch.obs, a0), cfg.num_q))
            pid = pid_step(state.pid, qc, qc_thres, cfg.pid)
            loss = (jnp.mean(-q + alpha * (mmd - cfg.mmd_threshold))
                    + jnp.mean(pid.lam * (qc - qc_thres)))
            return loss, (pid, mmd.mean(), qc.mean())

        state, pi_loss, (pid, mmd, qc_pi) = adam_step(state, "actor", actor_loss, cfg.actor_lr)
        log_alpha = jnp.clip(state.log_alpha + cfg.alpha_lr * alpha * (mmd - cfg.mmd_threshold),
                             -5.0, 5.0)
        target = {name: soft_update(state.target[name], state.params[name], cfg.tau)
                  for name in state.target}
        state = state._replace(target=target, pid=pid, log_alpha=log_alpha, step=state.step + 1)
        return state, {"vae_loss": vae_loss, "critic_loss": q_loss, "cost_critic_loss": qc_loss,
                       "actor_loss": pi_loss, "qc": qc_pi, "lambda": pid.lam, "mmd": mmd,
                       "alpha": jnp.exp(log_alpha)}

    def act(params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        return jnp.tanh(actor.apply(params["actor"], obs)[0])

    return Algorithm(init, update, act)


__all__ = ["make"]
