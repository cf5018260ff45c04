"""PPO-Lagrangian on our MJX tasks: one pure `train(key, schedule)`, vmappable over runs.

    train = make_train(cfg)                        # cfg: ExpertConfig
    out = jax.jit(train)(key, CostSchedule(25, 25).as_array())
    out = jax.jit(jax.vmap(train))(keys, schedules)   # several experts in one call

Each round resets every env at once and drives one whole episode (fixed horizon, no early
termination, so no per-step auto-reset select over the env state is needed), cut into rollouts
of `rollout_len` steps with one PPO update after each. The PID Lagrangian multiplier is updated
before each update from the rollout's cost rate times the episode length, an unbiased estimate
of the episode cost. Advantages are combined as (A_r - lambda A_c) / (1 + lambda) (A_r
standardised, A_c centred). Outputs per round: the episode totals (the learning curve) and a
snapshot of the actor with its observation normaliser, which `experts.collect` rolls out.
The key of round r is `fold_in(key, r)`, so `run_rounds` in chunks gives the same bits.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from safecdt_jax import envs
from safecdt_jax.experts.config import ExpertConfig
from safecdt_jax.experts.networks import (
    ObsNorm,
    action_dist,
    gaussian_log_prob,
    init_networks,
    value,
)

NETS = ("actor", "reward_critic", "cost_critic")


class PID(NamedTuple):
    """PID Lagrangian state: the multiplier, the error integral and the smoothed cost."""

    lam: jax.Array
    integral: jax.Array
    cost_ema: jax.Array


class Runner(NamedTuple):
    """Everything a run carries from one round to the next."""

    params: dict
    opt_state: dict
    norm: ObsNorm
    pid: PID
    key: jax.Array
    round: jax.Array


def gae(rewards: jax.Array, values: jax.Array, last_value: jax.Array, gamma: float,
        lam: float) -> tuple[jax.Array, jax.Array]:
    """Generalised advantage estimates and value targets of one rollout with no episode end
    inside it (the rollout's end is bootstrapped with `last_value`, also at a time limit).

    rewards, values: [L, ...]; last_value: [...]. Returns (advantages, returns), [L, ...].
    """
    def body(carry, xs):
        adv, next_v = carry
        r, v = xs
        adv = r + gamma * next_v - v + gamma * lam * adv
        return (adv, v), adv

    _, adv = jax.lax.scan(body, (jnp.zeros_like(last_value), last_value), (rewards, values),
                          reverse=True)
    return adv, adv + values


def pid_step(pid: PID, episode_cost: jax.Array, limit: jax.Array, kp: float, ki: float,
             kd: float, ema: float) -> PID:
    """One PID Lagrangian update (Stooke et al. 2020): error e = cost - limit; integral
    I <- max(0, I + e); smoothed cost s <- ema s + (1 - ema) cost; derivative
    D = max(0, s - s_prev); lambda = max(0, kp e + ki I + kd D). Costs are episode totals."""
    error = episode_cost - limit
    integral = jnp.maximum(0.0, pid.integral + error)
    smoothed = ema * pid.cost_ema + (1 - ema) * episode_cost
    derivative = jnp.maximum(0.0, smoothed - pid.cost_ema)
    lam = jnp.maximum(0.0, kp * error + ki * integral + kd * derivative)
    return PID(lam, integral, smoothed)


def cost_limit(schedule: jax.Array, progress: jax.Array) -> jax.Array:
    """The limit of `schedule` ([start, end, begin, finish]) at training progress in [0, 1]."""
    start, end, begin, finish = schedule[0], schedule[1], schedule[2], schedule[3]
    span = jnp.maximum(finish - begin, 1e-9)
    frac = jnp.clip((progress - begin) / span, 0.0, 1.0)
    frac = jnp.where(progress >= finish, 1.0, frac)
    return start + (end - start) * frac


def make_train(cfg: ExpertConfig):
    """Returns `train(key, schedule) -> (Runner, outputs)` for `cfg`, and exposes its pieces as
    attributes: `train.init(key)`, `train.run_rounds(runner, schedule, n)` (a jittable chunk of
    rounds) and `train.policy(snapshot, obs, key)`.

    outputs (leading axis = rounds): 'return', 'cost' (mean episode totals over the round's
    envs, raw units), 'cost_limit', 'lambda' (at the round's end), 'std' (mean action std),
    'snapshot' ({'actor', 'norm'}: the actor after the round and the normaliser it reads with).
    """
    env, env_params = envs.make(cfg.task)
    obs_dim, act_dim = env.observation_size, env.action_size
    horizon, n_envs, length = cfg.horizon, cfg.num_envs, cfg.rollout_len
    total_updates = cfg.rounds * cfg.updates_per_round
    tx = optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm), optax.adam(cfg.lr))
    hidden = cfg.hidden

    def sample(actor: dict, norm: ObsNorm, obs: jax.Array, key: jax.Array):
        """(normalised obs, action, mean, std) of the Gaussian policy at raw `obs`."""
        z = norm.apply(obs, cfg.obs_var_floor, cfg.obs_clip)
        mean, std = action_dist(actor, z, hidden, cfg.min_std)
        return z, mean + std * jax.random.normal(key, mean.shape), mean, std

    def policy(snapshot: dict, obs: jax.Array, key: jax.Array) -> jax.Array:
        """A stochastic action [.., act_dim] of a snapshot at raw observations `obs`."""
        return sample(snapshot["actor"], snapshot["norm"], obs, key)[1]

    def init(key: jax.Array) -> Runner:
        k_net, k_run = jax.random.split(key)
        net = init_networks(k_net, obs_dim, act_dim, hidden, cfg.init_std)
        zero = jnp.float32(0.0)
        return Runner(params=net, opt_state={k: tx.init(net[k]) for k in NETS},
                      norm=ObsNorm.create(obs_dim), pid=PID(zero, zero, zero), key=k_run,
                      round=jnp.int32(0))

    def rollout(params, norm, states, key):
        def step(states, k):
            z, action, mean, std = sample(params["actor"], norm, states.obs, k)
            nxt = jax.vmap(env.step, in_axes=(0, 0, None))(states, jnp.clip(action, -1, 1),
                                                            env_params)
            out = dict(raw_obs=states.obs, obs=z, action=action,
                       logp=gaussian_log_prob(action, mean, std), reward=nxt.reward,
                       cost=nxt.cost, v_r=value(params["reward_critic"], z, hidden),
                       v_c=value(params["cost_critic"], z, hidden))
            return nxt, out

        return jax.lax.scan(step, states, jax.random.split(key, length))


    def loss_fn(net, batch):
        mean, std = action_dist(net["actor"], batch["obs"], hidden, cfg.min_std)
        logp = gaussian_log_prob(batch["action"], mean, std)
        ratio = jnp.exp(logp - batch["logp"])
        adv = batch["adv"]
        clipped = jnp.clip(ratio, 1 - cfg.clip_eps, 1 + cfg.clip_eps)
        pg = -jnp.mean(jnp.minimum(ratio * adv, clipped * adv))
        entropy = jnp.mean(jnp.sum(jnp.log(std) + 0.5 * jnp.log(2 * jnp.pi * jnp.e), -1))
        v_r = value(net["reward_critic"], batch["obs"], hidden)
        v_c = value(net["cost_critic"], batch["obs"], hidden)
        # The three networks share no weights, so one summed loss gives each its own gradient.
        return (pg - cfg.ent_coef * entropy + 0.5 * jnp.mean((v_r - batch["ret_r"]) ** 2)
                + 0.5 * jnp.mean((v_c - batch["ret_c"]) ** 2))

    def ppo_update(net, opt_state, batch, key):
        n = n_envs * length

        def epoch(carry, k):
            def minibatch(carry, idx):
                net, opt_state = carry
                mb = jax.tree.map(lambda x: x[idx], batch)
                grads = jax.grad(loss_fn)(net, mb)
                for name in NETS:
                    upd, opt_state[name] = tx.update(grads[name], opt_state[name], net[name])
                    net[name] = optax.apply_updates(net[name], upd)
                return (net, opt_state), None

            perm = jax.random.permutation(k, n).reshape(cfg.minibatches, -1)
            return jax.lax.scan(minibatch, carry, perm)[0], None

        (net, opt_state), _ = jax.lax.scan(epoch, (dict(net), dict(opt_state)),
                                           jax.random.split(key, cfg.epochs))
        return net, opt_state

    def update(carry, xs):
        runner, states = carry
        i, schedule = xs
        k_roll, k_ppo = jax.random.split(jax.random.fold_in(runner.key, i))
        states, traj = rollout(runner.params, runner.norm, states, k_roll)
        z_last = runner.norm.apply(states.obs, cfg.obs_var_floor, cfg.obs_clip)
        adv_r, ret_r = gae(traj["reward"], traj["v_r"],
                           value(runner.params["reward_critic"], z_last, hidden),
                           cfg.gamma, cfg.gae_lambda)
        adv_c, ret_c = gae(traj["cost"], traj["v_c"],
                           value(runner.params["cost_critic"], z_last, hidden),
                           cfg.gamma, cfg.gae_lambda)
        limit = cost_limit(schedule, (runner.round * cfg.updates_per_round + i) / total_updates)
        pid = pid_step(runner.pid, traj["cost"].mean() * horizon, limit, cfg.pid_kp,
                       cfg.pid_ki, cfg.pid_kd, cfg.pid_ema)
        adv_r = (adv_r - adv_r.mean()) / (adv_r.std() + 1e-8)
        adv = (adv_r - pid.lam * (adv_c - adv_c.mean())) / (1 + pid.lam)
        batch = dict(obs=traj["obs"], action=traj["action"], logp=traj["logp"], adv=adv,
                     ret_r=ret_r, ret_c=ret_c)
        batch = jax.tree.map(lambda x: x.reshape(n_envs * length, *x.shape[2:]), batch)
        net, opt_state = ppo_update(runner.params, runner.opt_state, batch, k_ppo)
        runner = runner._replace(params=net, opt_state=opt_state, pid=pid,
                                 norm=runner.norm.update(traj["raw_obs"]))
        return (runner, states), (traj["reward"].sum(0), traj["cost"].sum(0), limit)

    def one_round(runner: Runner, schedule: jax.Array):
        key = jax.random.fold_in(runner.key, runner.round)
        k_reset, k_upd = jax.random.split(key)
        states = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, n_envs),
                                                         env_params)
        inner = runner._replace(key=k_upd)
        steps = (jnp.arange(cfg.updates_per_round), jnp.broadcast_to(
            schedule, (cfg.updates_per_round, *schedule.shape)))
        (inner, _), (rewards, costs, limits) = jax.lax.scan(update, (inner, states), steps)
        runner = inner._replace(key=runner.key, round=runner.round + 1)
        std = jnp.exp(jnp.maximum(runner.params["actor"]["log_std"], jnp.log(cfg.min_std)))
        out = {"return": rewards.sum(0).mean(), "cost": costs.sum(0).mean(),
               "cost_limit": limits[-1], "lambda": runner.pid.lam, "std": std.mean(),
               "snapshot": {"actor": runner.params["actor"], "norm": runner.norm}}
        return runner, out

    def run_rounds(runner: Runner, schedule: jax.Array, n: int):
        """`n` rounds from `runner` (n static): (runner, outputs with leading axis n)."""
        return jax.lax.scan(lambda r, _: one_round(r, schedule), runner, None, length=n)

    def train(key: jax.Array, schedule: jax.Array):
        return run_rounds(init(key), schedule, cfg.rounds)

    train.init, train.run_rounds, train.policy, train.cfg = init, run_rounds, policy, cfg
    return train


__all__ = ["NETS", "PID", "Runner", "cost_limit", "gae", "make_train", "pid_step"]
