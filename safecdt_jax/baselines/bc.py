"""Behaviour cloning baselines (OSRL's BC-All and BC-Safe): is a data set imitable at all?

A per-step MLP from observation to action, fitted by mean squared error, then rolled out in the
task. It sees no return or cost target and no history, so it answers a question the CDT cannot
answer about itself: whether the actions in the data can be cloned from the observations. With
`max_cost` it keeps only the episodes of cost <= max_cost (BC-Safe); its rollout cost is then
what plain imitation of the safe part of the data achieves, a reference that a CDT asked for a
low cost should match. With `min_cost` too it clones one cost band: clones of successive bands
show whether the data's cost levels survive imitation at all, which a CDT conditioned on a cost
target needs (on CarGoal1 they do not: every band's clone costs about 50 per episode;
docs/METHOD.md section 9). (Collector-v4 data, 20 episodes: BC-Safe at
max_cost 0 costs 64-75 per episode on CarGoal1, as a `cpu` CDT trained on careful-only data does,
37-73; on CarCircle1 it also costs 75, where the CDT, reading its context, gets 4-7 at low
cost targets.)

    policy, loss = fit_bc(jax.random.PRNGKey(0), data, BCConfig(max_cost=0.0))
    policies, losses = fit_bc_seeds(jax.random.split(jax.random.PRNGKey(0), 3), data)  # 3 seeds
    returns, costs = evaluate_bc(jax.random.PRNGKey(1), "CarGoal1", policy, episodes=20)

Units: observations standardised by the selected data's mean and std (floored at `std_floor`);
actions learnt in units of the data's largest |action| per dimension (the Car's wheel commands
stay within +-0.02), so the loss is a fraction of each actuator's used range, squared.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from safecdt_jax.data.dataset import Dataset
from safecdt_jax.data.windows import episode_costs
from safecdt_jax.pretrain.normalize import transition_norm


@dataclasses.dataclass(frozen=True)
class BCConfig:
    """Behaviour cloning settings.

    Attributes:
      hidden: width of each hidden ReLU layer (256).
      layers: hidden layers (2).
      steps: Adam updates (20,000: about 5 passes over 1,000 Goal episodes at batch 256).
      batch: transitions per update (256), drawn uniformly with replacement.
      lr: Adam learning rate (3e-4).
      max_cost: keep only episodes of cost <= this (BC-Safe); None: no upper bound.
      min_cost: keep only episodes of cost >= this; None: no lower bound (None and None: BC-All).
      std_floor: smallest observation std used to standardise (0.01; constant sensors).
      chunk: updates per jitted `lax.scan` call (1,000).
    """

    hidden: int = 256
    layers: int = 2
    steps: int = 20_000
    batch: int = 256
    lr: float = 3e-4
    max_cost: float | None = None
    min_cost: float | None = None
    std_floor: float = 0.01
    chunk: int = 1_000

    def __post_init__(self):
        for name in ("hidden", "layers", "steps", "batch", "chunk"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"BCConfig.{name} must be an integer >= 1, got {value!r}")
        for name in ("lr", "std_floor"):
            if not getattr(self, name) > 0:
                raise ValueError(f"BCConfig.{name} must be positive, got {getattr(self, name)!r}")
        for name in ("max_cost", "min_cost"):
            value = getattr(self, name)
            if value is not None and not value >= 0:
                raise ValueError(f"BCConfig.{name} must be >= 0 or None, got {value!r}")
        if None not in (self.min_cost, self.max_cost) and self.min_cost > self.max_cost:
            raise ValueError(f"BCConfig.min_cost ({self.min_cost:g}) must be <= max_cost "
                             f"({self.max_cost:g})")


class BCPolicy(NamedTuple):
    """A fitted clone: MLP layers [(W, b)], observation mean/std [obs_dim], action scale [act]."""

    layers: list
    obs_mean: jax.Array
    obs_std: jax.Array
    action_scale: jax.Array


def bc_action(policy: BCPolicy, obs: jax.Array) -> jax.Array:
    """The clone's action for observations [..., obs_dim], in the env's action units."""
    x = (obs - policy.obs_mean) / policy.obs_std
    for w, b in policy.layers[:-1]:
        x = jax.nn.relu(x @ w + b)
    w, b = policy.layers[-1]
    return (x @ w + b) * policy.action_scale


def cloned_episodes(data: Dataset, max_cost: float | None,
                    min_cost: float | None = None) -> np.ndarray:
    """bool [n_episodes]: the episodes of cost in [min_cost, max_cost] (a None bound is open).
    Raises ValueError naming the band and the data's cost range if no episode qualifies."""
    costs = episode_costs(data)
    keep = np.ones(data.n_episodes, bool)
    if max_cost is not None:
        keep &= costs <= max_cost
    if min_cost is not None:
        keep &= costs >= min_cost
    if not keep.any():
        raise ValueError(f"no episode has cost {cost_band(max_cost, min_cost)} (episode costs "
                         f"span {costs.min():g}-{costs.max():g})")
    return keep


def cost_band(max_cost: float | None, min_cost: float | None = None) -> str:
    """The band `cloned_episodes` keeps, as text: '<= 0', '>= 20', 'in [10, 30]' or 'any'."""
    if min_cost is None:
        return "any" if max_cost is None else f"<= {max_cost:g}"
    return f">= {min_cost:g}" if max_cost is None else f"in [{min_cost:g}, {max_cost:g}]"


def select_transitions(data: Dataset, max_cost: float | None,
                       min_cost: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(observations [N, obs_dim], actions [N, act_dim]) of the valid steps of the episodes
    `cloned_episodes(data, max_cost, min_cost)` keeps."""
    valid = data.valid_steps & cloned_episodes(data, max_cost, min_cost)[:, None]
    return (np.asarray(data.observations)[valid].astype(np.float32),
            np.asarray(data.actions)[valid].astype(np.float32))


def fit_bc_seeds(keys: jax.Array, data: Dataset, cfg: BCConfig = BCConfig()
                 ) -> tuple[BCPolicy, np.ndarray]:
    """Fits one clone per key of `keys` [seeds] to `data` (the episodes `cfg.min_cost` /
    `cfg.max_cost` select) by minibatch MSE, every seed in the same compiled, vmapped program.

    Returns the policies stacked (every leaf with a leading seed axis; the normalisation, a
    function of the data, is shared) and the mean loss of each chunk of `cfg.chunk` updates
    [seeds, chunks] (squared fraction of each action's scale, averaged over action dims). Pure
    given `keys`: same keys, same bits.
    """
    obs, actions = select_transitions(data, cfg.max_cost, cfg.min_cost)
    norm = transition_norm(obs, actions, cfg.std_floor, act_floor=1e-6)
    sizes = [obs.shape[1]] + [cfg.hidden] * cfg.layers + [actions.shape[1]]
    obs_mean, obs_std = jnp.asarray(norm.obs_mean), jnp.asarray(norm.obs_std)
    act_scale = jnp.asarray(norm.act_scale)
    obs_d, act_d = jnp.asarray(obs), jnp.asarray(actions)
    opt = optax.adam(cfg.lr)

    def init(key):
        k_init, k_train = jax.random.split(key)
        layers = [(jax.random.normal(k, (m, n)) / np.sqrt(m), jnp.zeros(n))
                  for k, (m, n) in zip(jax.random.split(k_init, len(sizes) - 1),
                                       itertools.pairwise(sizes), strict=True)]
        return layers, opt.init(layers), k_train

    def loss_fn(layers, idx):
        pred = bc_action(BCPolicy(layers, obs_mean, obs_std, act_scale), obs_d[idx])
        return jnp.mean(((pred - act_d[idx]) / act_scale) ** 2)

    def chunk(layers, opt_state, key):
        def update(carry, k):
            layers, opt_state = carry
            idx = jax.random.randint(k, (cfg.batch,), 0, obs_d.shape[0])
            loss, grads = jax.value_and_grad(loss_fn)(layers, idx)
            updates, opt_state = opt.update(grads, opt_state, layers)
            return (optax.apply_updates(layers, updates), opt_state), loss

        (layers, opt_state), losses = jax.lax.scan(update, (layers, opt_state),
                                                   jax.random.split(key, cfg.chunk))
        return layers, opt_state, losses.mean()

    layers, opt_state, k_train = jax.jit(jax.vmap(init))(keys)
    n_chunks = -(-cfg.steps // cfg.chunk)  # the last chunk may overshoot `steps` by < chunk
    chunk_keys = jax.vmap(lambda k: jax.random.split(k, n_chunks))(k_train)  # [seeds, chunks]
    run_chunk = jax.jit(jax.vmap(chunk))
    history = []
    for c in range(n_chunks):  # one call per chunk: a long fit reports as it goes
        layers, opt_state, loss = run_chunk(layers, opt_state, chunk_keys[:, c])
        history.append(np.asarray(loss))
    seeds = keys.shape[0]
    policy = BCPolicy(layers, *(jnp.broadcast_to(x, (seeds, *x.shape))
                                for x in (obs_mean, obs_std, act_scale)))
    return policy, np.stack(history, axis=1)


def fit_bc(key: jax.Array, data: Dataset, cfg: BCConfig = BCConfig()
           ) -> tuple[BCPolicy, np.ndarray]:
    """One clone (`fit_bc_seeds` with the single key `key`): the policy and the mean loss of
    each chunk of `cfg.chunk` updates [chunks]."""
    policy, history = fit_bc_seeds(jnp.asarray(key)[None], data, cfg)
    return jax.tree.map(lambda x: x[0], policy), history[0]


def evaluate_bc(key: jax.Array, task: str, policy: BCPolicy, episodes: int = 20
                ) -> tuple[np.ndarray, np.ndarray]:
    """(returns [episodes], costs [episodes]) of the clone in `task`, full-length episodes, the
    mean action every step (no noise). One jitted, vmapped program."""
    from safecdt_jax import envs
    from safecdt_jax.envs.rollout import run_episode

    env, params = envs.make(task)
    if policy.obs_mean.shape[0] != env.observation_size:
        raise ValueError(f"the clone reads {policy.obs_mean.shape[0]} observation dims, "
                         f"{task} gives {env.observation_size}")
    run = jax.jit(jax.vmap(lambda k: run_episode(
        env, params, k, lambda _, state: bc_action(policy, state.obs))))
    out = jax.device_get(run(jax.random.split(key, episodes)))
    return np.asarray(out["return"]), np.asarray(out["cost"])


__all__ = ["BCConfig", "BCPolicy", "bc_action", "cloned_episodes", "evaluate_bc", "fit_bc",
           "fit_bc_seeds", "select_transitions"]
