"""The baselines' networks (OSRL's shapes): critic ensembles, the BCQ-style VAE, the BCQ
perturbation actor and the squashed-Gaussian actor. Actions are in [-1, 1] (max_action 1: the
data's actions are rescaled per dimension before training, `baselines.data`)."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp


class MLP(nn.Module):
    """Two hidden layers of `hidden` units (ReLU, or tanh when `tanh`), a linear output."""

    hidden: int
    out: int
    tanh: bool = False

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        act = nn.tanh if self.tanh else nn.relu
        for _ in range(2):
            x = act(nn.Dense(self.hidden)(x))
        return nn.Dense(self.out)(x)


class QEnsemble(nn.Module):
    """`num` independent Q(s, a) MLPs; returns their values stacked [num, ...]."""

    hidden: int
    num: int

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        batched = nn.vmap(MLP, variable_axes={"params": 0}, split_rngs={"params": True},
                          in_axes=None, out_axes=0, axis_size=self.num)
        return batched(self.hidden, 1)(jnp.concatenate([obs, action], -1))[..., 0]


def double_min(heads: jax.Array, num: int) -> tuple[jax.Array, jax.Array]:
    """OSRL's `EnsembleDoubleQCritic` read-out: heads [2 num, ...] of one `QEnsemble` are two
    ensembles Q1, Q2; each prediction is the min over its ensemble. Returns (q1, q2)."""
    return heads[:num].min(0), heads[num:].min(0)


class VAE(nn.Module):
    """BCQ's conditional VAE of the behaviour actions: encoder [s, a] -> (mu, log std) of a
    latent of 2 x act_dim, decoder [s, z] -> tanh action (or its pre-tanh value)."""

    hidden: int
    act_dim: int

    def setup(self):
        self.encoder = MLP(self.hidden, 4 * self.act_dim)
        self.decoder = MLP(self.hidden, self.act_dim)

    def encode(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(mu, log std) of q(z | s, a), log std clipped to [-4, 15]."""
        out = self.encoder(jnp.concatenate([obs, action], -1))
        mu, log_std = jnp.split(out, 2, axis=-1)
        return mu, jnp.clip(log_std, -4.0, 15.0)

    def decode(self, obs: jax.Array, z: jax.Array, pre_tanh: bool = False) -> jax.Array:
        """The decoded action at latent `z` (pre-tanh when `pre_tanh`, as BEAR's MMD uses)."""
        u = self.decoder(jnp.concatenate([obs, z], -1))
        return u if pre_tanh else jnp.tanh(u)

    def sample(self, key: jax.Array, obs: jax.Array, pre_tanh: bool = False) -> jax.Array:
        """A decoded action from the clipped prior z ~ N(0, I) in [-0.5, 0.5]."""
        z = jnp.clip(jax.random.normal(key, (*obs.shape[:-1], 2 * self.act_dim)), -0.5, 0.5)
        return self.decode(obs, z, pre_tanh)

    def __call__(self, key: jax.Array, obs: jax.Array, action: jax.Array):
        """(reconstruction, mu, log std) of a pass through the encoder and decoder."""
        mu, log_std = self.encode(obs, action)
        z = mu + jnp.exp(log_std) * jax.random.normal(key, mu.shape)
        return self.decode(obs, z), mu, log_std


class Perturbation(nn.Module):
    """BCQ's actor: a = clip(a_vae + phi xi(s, a_vae), -1, 1), xi a tanh MLP in [-1, 1]."""

    hidden: int
    act_dim: int
    phi: float

    @nn.compact
    def __call__(self, obs: jax.Array, vae_action: jax.Array) -> jax.Array:
        xi = jnp.tanh(MLP(self.hidden, self.act_dim, tanh=True)(
            jnp.concatenate([obs, vae_action], -1)))
        return jnp.clip(vae_action + self.phi * xi, -1.0, 1.0)


class SquashedGaussian(nn.Module):
    """BEAR's and CPQ's actor: u ~ N(mu(s), sigma(s)), a = tanh(u), log sigma in [-20, 2].
    Returns (mu, log sigma)."""

    hidden: int
    act_dim: int

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = obs
        for _ in range(2):
            x = nn.relu(nn.Dense(self.hidden)(x))
        return nn.Dense(self.act_dim)(x), jnp.clip(nn.Dense(self.act_dim)(x), -20.0, 2.0)


def squashed_sample(key: jax.Array, mu: jax.Array, log_std: jax.Array):
    """(tanh action, pre-tanh sample, log-prob of the action in nats with the tanh correction)."""
    u = mu + jnp.exp(log_std) * jax.random.normal(key, mu.shape)
    logp = jnp.sum(-0.5 * ((u - mu) / jnp.exp(log_std)) ** 2 - log_std
                   - 0.5 * jnp.log(2 * jnp.pi), -1)
    # log(1 - tanh(u)^2) written stably, as SAC implementations do.
    logp -= jnp.sum(2 * (jnp.log(2.0) - u - jax.nn.softplus(-2 * u)), -1)
    return jnp.tanh(u), u, logp


__all__ = [
    "MLP",
    "VAE",
    "Perturbation",
    "QEnsemble",
    "SquashedGaussian",
    "double_min",
    "squashed_sample",
]
