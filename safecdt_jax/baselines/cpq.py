"""Constraints Penalized Q-learning (OSRL's `CPQ`): the reward critic's Bellman target gives no
future value to next states whose cost value under the policy exceeds the threshold, the cost
critic is (in the CPQ paper) pushed up on out-of-distribution actions flagged by the VAE's KL,
and the actor maximises the reward value only where the cost value is within the threshold.

OSRL's code computes the OOD term with the target cost critic under no gradient, so its cost
critic learns by plain TD; that is the default here (`cpq_ood_grad=False`), the paper's version
a switch. Each step: VAE -> reward critic -> cost critic and alpha -> actor -> soft targets.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from safecdt_jax.baselines.common import (
    Algorithm,
    TrainState,
    Transitions,
    adam_step,
    gaussian_kl,
    init_networks,
    regress_critic,
    repeat,
    soft_update_targets,
    update_vae,
)
from safecdt_jax.baselines.config import BaselineConfig
from safecdt_jax.baselines.networks import VAE, QEnsemble, SquashedGaussian, squashed_sample


def ood_mask(kl: jax.Array, quantile: float) -> jax.Array:
    """1.0 where a sampled action's VAE KL [B, n] reaches the batch's `quantile`, else 0.0."""
    return (kl >= jnp.quantile(kl, quantile)).astype(jnp.float32)


def make(cfg: BaselineConfig, obs_dim: int, act_dim: int, qc_thres: float) -> Algorithm:
    """CPQ for observations of `obs_dim`, actions of `act_dim`; `qc_thres` is the per-step
    threshold of `common.qc_threshold` (the masks use it, the OOD term `qc_scalar` times it)."""
    actor = SquashedGaussian(cfg.hidden, act_dim)
    critic = QEnsemble(cfg.hidden, cfg.num_q)
    vae = VAE(cfg.vae_hidden, act_dim)
    q_thres, ood_thres = qc_thres, cfg.qc_scalar * qc_thres
    n = cfg.next_actions

    def init(key: jax.Array) -> TrainState:
        return init_networks(key, cfg, actor, critic, vae, obs_dim, act_dim, False)

    def update(state: TrainState, batch: Transitions, key: jax.Array):
        k_vae, k_next, k_ood, k_pi = jax.random.split(key, 4)
        state, vae_loss = update_vae(state, vae, batch, k_vae, cfg.vae_lr, cfg.vae_beta)

        next_act, _, _ = squashed_sample(k_next, *actor.apply(state.params["actor"],
                                                              batch.next_obs))
        q_next = critic.apply(state.target["critic"], batch.next_obs, next_act).min(0)
        qc_next = critic.apply(state.target["cost_critic"], batch.next_obs, next_act).min(0)
        safe_next = (qc_next <= q_thres).astype(jnp.float32)
        y = cfg.reward_scale * batch.reward + cfg.gamma * (1.0 - batch.done) * safe_next * q_next
        state, q_loss = regress_critic(state, "critic", critic, batch, y, cfg.critic_lr)

        obs_n = repeat(batch.obs, n)
        sampled, _, _ = squashed_sample(k_ood, *actor.apply(state.params["actor"], obs_n))
        sampled = jax.lax.stop_gradient(sampled)
        mu, log_std = vae.apply(state.params["vae"], obs_n, sampled, method=VAE.encode)
        mask = ood_mask(gaussian_kl(mu, log_std).mean(-1), cfg.ood_quantile)
        yc = jax.lax.stop_gradient(cfg.cost_scale * batch.cost + cfg.gamma * qc_next)
        alpha = jnp.exp(state.log_alpha)

        def cost_loss(params):
            heads = critic.apply(params, batch.obs, batch.action)
            td = jnp.sum(jnp.mean((heads - yc) ** 2, axis=-1))
            source = params if cfg.cpq_ood_grad else state.target["cost_critic"]
            qc_ood = mask * critic.apply(source, obs_n, sampled).min(0)
            if not cfg.cpq_ood_grad:
                qc_ood = jax.lax.stop_gradient(qc_ood)
            qc_ood = qc_ood.mean()
            return td - alpha * (qc_ood - ood_thres), (td, qc_ood)

        state, _, (qc_loss, qc_ood) = adam_step(state, "cost_critic", cost_loss,
                                                 cfg.critic_lr)
        log_alpha = jnp.clip(state.log_alpha + cfg.alpha_lr * alpha * (ood_thres - qc_ood),
                             -5.0, 5.0)

        def actor_loss(actor_params):
            a, _, _ = squashed_sample(k_pi, *actor.apply(actor_params, batch.obs))
            q = critic.apply(state.params["critic"], batch.obs, a).min(0)
            qc = critic.apply(state.params["cost_critic"], batch.obs, a).min(0)
            safe = jax.lax.stop_gradient((qc <= q_thres).astype(jnp.float32))
            return -jnp.mean(safe * q), qc.mean()

        state, pi_loss, qc_pi = adam_step(state, "actor", actor_loss, cfg.actor_lr)
        state = state._replace(target=soft_update_targets(state, cfg.tau), log_alpha=log_alpha,
                               step=state.step + 1)
        return state, {"vae_loss": vae_loss, "critic_loss": q_loss, "cost_critic_loss": qc_loss,
                       "actor_loss": pi_loss, "qc": qc_pi, "qc_ood": qc_ood,
                       "alpha": jnp.exp(log_alpha)}

    def act(params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        return jnp.tanh(actor.apply(params["actor"], obs)[0])

    return Algorithm(init, update, act)


__all__ = ["make", "ood_mask"]
