"""BCQ-Lagrangian (OSRL's `BCQL`): a VAE of the behaviour actions, a small perturbation actor on
its samples, reward and cost double-ensemble critics, and a PID Lagrangian that penalises the
actor's per-step cost value above the threshold.

Each step: VAE -> reward critic -> cost critic -> actor -> soft target updates.
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
    pid_step,
    repeat,
    soft_update_targets,
    update_double_critics,
    update_vae,
)
from safecdt_jax.baselines.config import BaselineConfig
from safecdt_jax.baselines.networks import VAE, Perturbation, QEnsemble


def make(cfg: BaselineConfig, obs_dim: int, act_dim: int, qc_thres: float) -> Algorithm:
    """BCQL for observations of `obs_dim`, actions of `act_dim`, per-step cost threshold
    `qc_thres` (`common.qc_threshold`)."""
    actor = Perturbation(cfg.hidden, act_dim, cfg.phi)
    critic = QEnsemble(cfg.hidden, 2 * cfg.num_q)
    vae = VAE(cfg.vae_hidden, act_dim)
    n = cfg.next_actions

    def init(key: jax.Array) -> TrainState:
        return init_networks(key, cfg, actor, critic, vae, obs_dim, act_dim, True)

    def policy(actor_params, vae_params, obs, key):
        a_vae = vae.apply(vae_params, key, obs, method=VAE.sample)
        return actor.apply(actor_params, obs, a_vae)

    def update(state: TrainState, batch: Transitions, key: jax.Array):
        k_vae, k_next, k_pi = jax.random.split(key, 3)
        state, vae_loss = update_vae(state, vae, batch, k_vae, cfg.vae_lr, cfg.vae_beta)

        next_obs = repeat(batch.next_obs, n)
        next_act = policy(state.target["actor"], state.params["vae"], next_obs, k_next)
        state, q_loss, qc_loss = update_double_critics(state, critic, batch, next_obs, next_act,
                                                       cfg)

        def actor_loss(actor_params):
            a = policy(actor_params, state.params["vae"], batch.obs, k_pi)
            q = double_q(critic, state.params["critic"], batch.obs, a, cfg.num_q)
            qc = double_q(critic, state.params["cost_critic"], batch.obs, a, cfg.num_q)
            pid = pid_step(state.pid, qc, qc_thres, cfg.pid)
            return -q.mean() + jnp.mean(pid.lam * (qc - qc_thres)), (pid, qc.mean())

        state, pi_loss, (pid, qc_pi) = adam_step(state, "actor", actor_loss, cfg.actor_lr)
        state = state._replace(target=soft_update_targets(state, cfg.tau), pid=pid,
                               step=state.step + 1)
        return state, {"vae_loss": vae_loss, "critic_loss": q_loss, "cost_critic_loss": qc_loss,
                       "actor_loss": pi_loss, "qc": qc_pi, "lambda": pid.lam}

    def act(params: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        return policy(params["actor"], params["vae"], obs, key)

    return Algorithm(init, update, act)


__all__ = ["make"]
