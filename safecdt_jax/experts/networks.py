"""The expert's networks and its running observation normaliser (pure functions of params)."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


def _scaled_normal(gain: float):
    # Variance gain^2 / fan_in: the scale of an orthogonal init of that gain. Orthogonal init
    # itself needs a QR decomposition, and several LAPACK QRs in one vmapped CPU program
    # deadlocked jaxlib 0.10.2 on this machine (vmap over 2 seeds never returned).
    return nn.initializers.variance_scaling(gain**2, "fan_in", "normal")


class MLP(nn.Module):
    """tanh MLP, weights N(0, gain^2 / fan_in) (gain sqrt 2 hidden, `out_scale` output), zero
    biases."""

    hidden: Sequence[int]
    out: int
    out_scale: float = 1.0

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for width in self.hidden:
            x = nn.tanh(nn.Dense(width, kernel_init=_scaled_normal(np.sqrt(2)))(x))
        return nn.Dense(self.out, kernel_init=_scaled_normal(self.out_scale))(x)


def init_networks(key: jax.Array, obs_dim: int, act_dim: int, hidden: Sequence[int],
                  init_std: float) -> dict:
    """Parameters {'actor': {'mean', 'log_std' [act_dim]}, 'reward_critic', 'cost_critic'}."""
    k_a, k_r, k_c = jax.random.split(key, 3)
    x = jnp.zeros((obs_dim,))
    return {
        "actor": {"mean": MLP(tuple(hidden), act_dim, 0.01).init(k_a, x),
                  "log_std": jnp.full((act_dim,), jnp.log(init_std), jnp.float32)},
        "reward_critic": MLP(tuple(hidden), 1).init(k_r, x),
        "cost_critic": MLP(tuple(hidden), 1).init(k_c, x),
    }


def action_dist(actor: dict, obs: jax.Array, hidden: Sequence[int], min_std: float):
    """(mean, std) of the Gaussian policy at normalised observations `obs` [..., obs_dim]."""
    act_dim = actor["log_std"].shape[-1]
    mean = MLP(tuple(hidden), act_dim, 0.01).apply(actor["mean"], obs)
    log_std = jnp.maximum(actor["log_std"], jnp.log(min_std))
    return mean, jnp.broadcast_to(jnp.exp(log_std), mean.shape)


def value(critic: dict, obs: jax.Array, hidden: Sequence[int]) -> jax.Array:
    """A critic's value at normalised observations `obs` [..., obs_dim] -> [...]."""
    return MLP(tuple(hidden), 1).apply(critic, obs)[..., 0]


def gaussian_log_prob(x: jax.Array, mean: jax.Array, std: jax.Array) -> jax.Array:
    """Log density of the diagonal Gaussian, summed over the last axis (nats)."""
    z = (x - mean) / std
    return jnp.sum(-0.5 * z * z - jnp.log(std) - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


@struct.dataclass
class ObsNorm:
    """Running mean and variance of observations (raw units), from `count` samples."""

    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @classmethod
    def create(cls, obs_dim: int) -> ObsNorm:
        """No samples yet: mean 0, variance 1."""
        return cls(jnp.zeros(obs_dim), jnp.ones(obs_dim), jnp.float32(0.0))

    def update(self, batch: jax.Array) -> ObsNorm:
        """Merges a batch [..., obs_dim] (Chan et al.'s parallel mean/variance update)."""
        x = batch.reshape(-1, batch.shape[-1])
        n = jnp.float32(x.shape[0])
        b_mean, b_var = x.mean(0), x.var(0)
        total = self.count + n
        delta = b_mean - self.mean
        mean = self.mean + delta * n / total
        m2 = self.var * self.count + b_var * n + delta**2 * self.count * n / total
        return ObsNorm(mean, m2 / total, total)

    def apply(self, obs: jax.Array, var_floor: float, clip: float) -> jax.Array:
        """(obs - mean) / std, clipped to +-`clip`; channels with variance below `var_floor`
        read as 0, so a channel that never varied cannot blow up when it starts to."""
        live = self.var >= var_floor
        z = (obs - self.mean) / jnp.sqrt(jnp.where(live, self.var, 1.0))
        return jnp.clip(jnp.where(live, z, 0.0), -clip, clip)


__all__ = ["MLP", "ObsNorm", "action_dist", "gaussian_log_prob", "init_networks", "value"]
