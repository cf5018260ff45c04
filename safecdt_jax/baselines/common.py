"""Pieces the three Q-learning baselines share: transition batches, the per-step cost
threshold, the PID Lagrangian, soft-clipped double-Q targets, the VAE loss, BEAR's MMD and
soft target updates. All pure functions of arrays."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.baselines.networks import double_min
from safecdt_jax.data.dataset import Dataset, DatasetError
from safecdt_jax.pretrain.normalize import IONorm, transition_norm


class Transitions(NamedTuple):
    """Flat transitions (observations standardised, actions in [-1, 1] units): obs, next_obs
    [N, obs_dim], action [N, act_dim], reward, cost [N] (raw per-step values), done [N] (the
    episode's last step: DSRL's terminals | timeouts)."""

    obs: jax.Array
    next_obs: jax.Array
    action: jax.Array
    reward: jax.Array
    cost: jax.Array
    done: jax.Array


def transitions(data: Dataset, std_floor: float = 0.01) -> tuple[Transitions, IONorm]:
    """The valid steps of `data` as `Transitions`, with the norm that maps raw observations
    and actions to the networks' units. Raises DatasetError if the data hold NaN or inf."""
    valid = data.valid_steps
    obs = np.asarray(data.observations)[valid].astype(np.float32)
    next_obs = np.asarray(data.next_observations)[valid].astype(np.float32)
    action = np.asarray(data.actions)[valid].astype(np.float32)
    reward = np.asarray(data.rewards)[valid].astype(np.float32)
    cost = np.asarray(data.costs)[valid].astype(np.float32)
    for name, x in (("observations", obs), ("next_observations", next_obs),
                    ("actions", action), ("rewards", reward), ("costs", cost)):
        if not np.isfinite(x).all():
            raise DatasetError(f"the data set's {name} hold NaN or inf")
    last = np.arange(data.horizon)[None, :] == (np.asarray(data.lengths)[:, None] - 1)
    done = last[valid]
    norm = transition_norm(obs, action, std_floor, act_floor=1e-6)
    return Transitions(
        obs=jnp.asarray((obs - norm.obs_mean) / norm.obs_std),
        next_obs=jnp.asarray((next_obs - norm.obs_mean) / norm.obs_std),
        action=jnp.asarray(np.clip(action / norm.act_scale, -1.0, 1.0)),
        reward=jnp.asarray(reward), cost=jnp.asarray(cost),
        done=jnp.asarray(done.astype(np.float32))), norm


def sample_batch(key: jax.Array, data: Transitions, batch: int) -> Transitions:
    """`batch` transitions drawn uniformly with replacement."""
    idx = jax.random.randint(key, (batch,), 0, data.obs.shape[0])
    return jax.tree.map(lambda x: x[idx], data)


def qc_threshold(cost_limit: float, gamma: float, episode_len: int) -> float:
    """OSRL's per-step cost-value threshold: the discounted value of spending the episode
    budget `cost_limit` evenly over `episode_len` steps, B (1 - gamma^L) / ((1 - gamma) L)."""
    return cost_limit * (1.0 - gamma**episode_len) / ((1.0 - gamma) * episode_len)


class PID(NamedTuple):
    """PID Lagrangian state: the multiplier, the error integral and the previous error."""

    lam: jax.Array
    integral: jax.Array
    prev_error: jax.Array

    @classmethod
    def create(cls) -> PID:
        """Zero multiplier, integral and previous error."""
        z = jnp.float32(0.0)
        return cls(z, z, z)


def pid_step(pid: PID, qc: jax.Array, threshold: float,
             gains: tuple[float, float, float]) -> PID:
    """One PID update from the batch's cost values `qc` [B] of the policy's actions:
    e = mean(qc) - threshold, I <- max(0, I + e), D = max(0, e - e_prev),
    lambda = max(0, KP max(0, e) + KI I + KD D) (OSRL's `LagrangianPIDController`)."""
    kp, ki, kd = gains
    error = jnp.mean(qc - threshold)
    integral = jax.nn.relu(pid.integral + error)
    deriv = jax.nn.relu(error - pid.prev_error)
    lam = jax.nn.relu(kp * jax.nn.relu(error) + ki * integral + kd * deriv)
    return PID(jax.lax.stop_gradient(lam), jax.lax.stop_gradient(integral),
               jax.lax.stop_gradient(error))


def soft_clipped(q1: jax.Array, q2: jax.Array, lmbda: float) -> jax.Array:
    """lmbda min(q1, q2) + (1 - lmbda) max(q1, q2): BCQ's soft-clipped double Q."""
    return lmbda * jnp.minimum(q1, q2) + (1.0 - lmbda) * jnp.maximum(q1, q2)


def repeat(x: jax.Array, n: int) -> jax.Array:
    """[B, ...] -> [B, n, ...]: each row repeated n times (the next-action samples)."""
    return jnp.repeat(x[:, None], n, axis=1)


def gaussian_kl(mu: jax.Array, log_std: jax.Array) -> jax.Array:
    """KL(N(mu, exp(log_std)^2) || N(0, 1)) per element, nats."""
    return -0.5 * (1.0 + 2.0 * log_std - mu**2 - jnp.exp(2.0 * log_std))


def vae_loss(recon: jax.Array, action: jax.Array, mu: jax.Array, log_std: jax.Array,
             beta: float) -> jax.Array:
    """MSE(recon, action) + beta KL(q(z | s, a) || N(0, I)), the KL averaged over elements."""
    return jnp.mean((recon - action) ** 2) + beta * jnp.mean(gaussian_kl(mu, log_std))


def mmd_gaussian(x: jax.Array, y: jax.Array, sigma: float) -> jax.Array:
    """BEAR's MMD between sample sets x [B, n, d] and y [B, m, d] per row [B], with the kernel
    exp(-|a - b|^2 / (2 sigma)): sqrt(k_xx + k_yy - 2 k_xy + 1e-6)."""
    def k(a, b):
        d2 = jnp.sum((a[:, :, None] - b[:, None, :]) ** 2, -1)
        return jnp.exp(-d2 / (2.0 * sigma)).mean((1, 2))

    return jnp.sqrt(k(x, x) + k(y, y) - 2.0 * k(x, y) + 1e-6)


def soft_update(target, online, tau: float):
    """target <- (1 - tau) target + tau online, leaf by leaf."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


class TrainState(NamedTuple):
    """One run's training state: online `params` and `target` copies (dicts by network name),
    Adam states `opt` (same names as `params`), the PID Lagrangian, a hand-updated log alpha
    (BEAR's MMD dual, CPQ's OOD dual; unused by BCQL) and the number of steps taken."""

    params: dict
    target: dict
    opt: dict
    pid: PID
    log_alpha: jax.Array
    step: jax.Array


class Algorithm(NamedTuple):
    """An algorithm as three pure functions: `init(key) -> TrainState`, `update(state, batch,
    key) -> (state, metrics {name: scalar})`, `act(params, obs, key) -> action` (the action in
    [-1, 1] units; deterministic except for BCQL, which acts through one VAE sample as OSRL's
    does)."""

    init: object
    update: object
    act: object


def adam_step(state: TrainState, name: str, loss_fn, lr: float, *args):
    """Minimises `loss_fn(params[name], *args) -> (loss, aux)` by one Adam step on network
    `name`; returns (state with new params and opt state, loss, aux)."""
    import optax

    (loss, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params[name], *args)
    updates, opt = optax.adam(lr).update(grads, state.opt[name], state.params[name])
    params = dict(state.params, **{name: optax.apply_updates(state.params[name], updates)})
    return state._replace(params=params, opt=dict(state.opt, **{name: opt})), loss, aux


def init_state(params: dict, lrs: dict, targets: tuple[str, ...]) -> TrainState:
    """Fresh `TrainState`: Adam states for every network (learning rates `lrs` by name),
    target copies of the networks named in `targets`."""
    import optax

    return TrainState(params=params, target={n: params[n] for n in targets},
                      opt={n: optax.adam(lrs[n]).init(p) for n, p in params.items()},
                      pid=PID.create(), log_alpha=jnp.float32(0.0), step=jnp.int32(0))


def update_vae(state: TrainState, vae, batch: Transitions, key: jax.Array, lr: float,
               beta: float) -> tuple[TrainState, jax.Array]:
    """One Adam step of the behaviour VAE (network 'vae') on the batch; returns (state, loss)."""
    def loss_fn(params):
        recon, mu, log_std = vae.apply(params, key, batch.obs, batch.action)
        return vae_loss(recon, batch.action, mu, log_std, beta), None

    state, loss, _ = adam_step(state, "vae", loss_fn, lr)
    return state, loss


def max_soft_clipped(q_heads: jax.Array, num: int, lmbda: float) -> jax.Array:
    """Critic target value of the next state: heads [2 num, B, n] of the target double
    ensemble at n sampled next actions -> soft-clipped double Q, max over the samples [B]."""
    q1, q2 = double_min(q_heads, num)
    return soft_clipped(q1, q2, lmbda).max(-1)


def regress_critic(state: TrainState, name: str, critic, batch: Transitions, y: jax.Array,
                   lr: float) -> tuple[TrainState, jax.Array]:
    """One Adam step of critic `name` (a `QEnsemble`): the sum over its heads of the MSE
    against the (constant) target `y` [B]. Returns (state, loss)."""
    y = jax.lax.stop_gradient(y)

    def loss_fn(params):
        heads = critic.apply(params, batch.obs, batch.action)
        return jnp.sum(jnp.mean((heads - y) ** 2, axis=-1)), None

    state, loss, _ = adam_step(state, name, loss_fn, lr)
    return state, loss


def init_networks(key: jax.Array, cfg, actor, critic, vae, obs_dim: int, act_dim: int,
                  actor_reads_action: bool) -> TrainState:
    """Fresh `TrainState` of an actor, a reward and a cost critic (the same `critic` module,
    two parameter sets) and the behaviour VAE, with Adam states at `cfg`'s rates and target
    copies of actor and critics. `actor_reads_action`: the actor takes (obs, action) (BCQ's
    perturbation) rather than obs alone."""
    k_a, k_q, k_c, k_v, k_s = jax.random.split(key, 5)
    obs, act = jnp.zeros((1, obs_dim)), jnp.zeros((1, act_dim))
    params = {"actor": actor.init(k_a, obs, act) if actor_reads_action else actor.init(k_a, obs),
              "critic": critic.init(k_q, obs, act), "cost_critic": critic.init(k_c, obs, act),
              "vae": vae.init(k_v, k_s, obs, act)}
    lrs = {"actor": cfg.actor_lr, "critic": cfg.critic_lr, "cost_critic": cfg.critic_lr,
           "vae": cfg.vae_lr}
    return init_state(params, lrs, ("actor", "critic", "cost_critic"))


def double_q(critic, params, obs: jax.Array, action: jax.Array, num: int) -> jax.Array:
    """min(Q1, Q2) of a double ensemble (`QEnsemble` of 2 num heads) at (obs, action)."""
    return jnp.minimum(*double_min(critic.apply(params, obs, action), num))


def update_double_critics(state: TrainState, critic, batch: Transitions, next_obs: jax.Array,
                          next_act: jax.Array, cfg) -> tuple[TrainState, jax.Array, jax.Array]:
    """BCQL's and BEARL's critic steps: targets from the n sampled next actions [B, n, act]
    at the repeated next states (`max_soft_clipped` of the target ensembles), the reward one
    masked by done and the cost one not (as OSRL), each critic one Adam step. Returns (state,
    reward-critic loss, cost-critic loss)."""
    q_next = max_soft_clipped(critic.apply(state.target["critic"], next_obs, next_act),
                              cfg.num_q, cfg.lmbda)
    y = cfg.reward_scale * batch.reward + cfg.gamma * (1.0 - batch.done) * q_next
    state, q_loss = regress_critic(state, "critic", critic, batch, y, cfg.critic_lr)
    qc_next = max_soft_clipped(critic.apply(state.target["cost_critic"], next_obs, next_act),
                               cfg.num_q, cfg.lmbda)
    yc = cfg.cost_scale * batch.cost + cfg.gamma * qc_next
    state, qc_loss = regress_critic(state, "cost_critic", critic, batch, yc, cfg.critic_lr)
    return state, q_loss, qc_loss


def soft_update_targets(state: TrainState, tau: float) -> dict:
    """Every target network moved `tau` toward its online network."""
    return {name: soft_update(state.target[name], state.params[name], tau)
            for name in state.target}


__all__ = [
    "PID",
    "Algorithm",
    "TrainState",
    "Transitions",
    "adam_step",
    "double_q",
    "gaussian_kl",
    "init_networks",
    "init_state",
    "max_soft_clipped",
    "mmd_gaussian",
    "pid_step",
    "qc_threshold",
    "regress_critic",
    "repeat",
    "sample_batch",
    "soft_clipped",
    "soft_update",
    "soft_update_targets",
    "transitions",
    "update_double_critics",
    "update_vae",
    "vae_loss",
]
