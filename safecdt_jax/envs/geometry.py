"""Planar geometry shared by the tasks: rotations, pseudo-lidar and keepout placement."""

import jax
import jax.numpy as jnp

N_LIDAR_BINS = 16
FAR = 1e3  # where inactive objects are parked: beyond every lidar range and keepout test


def rot2(yaw: jax.Array) -> jax.Array:
    """2x2 rotation matrix (body to world) for a heading `yaw` in radians."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.array([[c, -s], [s, c]])


def to_body(points: jax.Array, agent_xy: jax.Array, yaw: jax.Array) -> jax.Array:
    """World points [N, 2] (m) expressed in the agent's body frame [N, 2] (m)."""
    return (points - agent_xy) @ rot2(yaw)


def pseudo_lidar(points: jax.Array, mask: jax.Array, agent_xy: jax.Array, yaw: jax.Array,
                 max_dist: float) -> jax.Array:
    """Safety-Gymnasium's 16-bin pseudo-lidar of object centres (not ray casting).

    Each active object at body-frame distance d and angle theta (bin 0 at body +x, counter-
    clockwise) reads s = max(0, D - d) / D in bin floor(theta / (2 pi / 16)) and, aliased, a*s
    in the next bin and (1 - a)*s in the previous one, a = frac(theta / bin width); bins keep
    the maximum over objects. Returns [16] readings in [0, 1].
    """
    rel = to_body(points, agent_xy, yaw)
    dist = jnp.linalg.norm(rel, axis=-1)
    theta = jnp.mod(jnp.arctan2(rel[:, 1], rel[:, 0]), 2 * jnp.pi)
    pos = theta / (2 * jnp.pi / N_LIDAR_BINS)
    # mod guards the theta == 2 pi rounding edge, which would index bin 16.
    b = jnp.mod(jnp.floor(pos).astype(jnp.int32), N_LIDAR_BINS)
    alias = pos - jnp.floor(pos)
    s = jnp.maximum(0.0, max_dist - dist) / max_dist * mask
    onehot = lambda i: jax.nn.one_hot(jnp.mod(i, N_LIDAR_BINS), N_LIDAR_BINS)
    contrib = jnp.maximum(onehot(b) * s[:, None], onehot(b + 1) * (alias * s)[:, None])
    contrib = jnp.maximum(contrib, onehot(b - 1) * ((1 - alias) * s)[:, None])
    return jnp.max(contrib, axis=0, initial=0.0)


def place(key: jax.Array, extent: jax.Array, keepout: float, placed: jax.Array,
          placed_keepout: jax.Array, placed_mask: jax.Array, n_candidates: int = 64) -> jax.Array:
    """Draws one position uniformly in [-extent + k, extent - k]^2 that keeps out of `placed`.

    A candidate is valid when its distance to every active placed object is at least the sum of
    the two keepouts. Safety-Gymnasium rejection-samples up to 100 times; here a fixed number of
    candidates is drawn at once and the first valid one is taken, so the program has static shape.
    If none is valid (very crowded layouts) the candidate with the largest margin is returned.
    Returns [2] (m).
    """
    half = extent - keepout
    cand = jax.random.uniform(key, (n_candidates, 2), minval=-half, maxval=half)
    dist = jnp.linalg.norm(cand[:, None, :] - placed[None, :, :], axis=-1)
    margin = dist - (keepout + placed_keepout)[None, :]
    margin = jnp.min(jnp.where(placed_mask[None, :] > 0, margin, jnp.inf), axis=1)
    valid = margin >= 0
    idx = jnp.where(jnp.any(valid), jnp.argmax(valid), jnp.argmax(margin))
    return cand[idx]


def place_all(key: jax.Array, extent: jax.Array, keepouts: jax.Array, active: jax.Array
              ) -> jax.Array:
    """Sequentially places objects (in order) with keepouts, as Safety-Gymnasium's layout does.

    keepouts [N] (m), active [N] 0/1. Inactive objects are parked at FAR, apart from each other.
    Returns positions [N, 2] (m).
    """
    n = keepouts.shape[0]
    keys = jax.random.split(key, n)

    def body(carry, i):
        pos, placed_mask = carry
        p = place(keys[i], extent, keepouts[i], pos, keepouts, placed_mask)
        p = jnp.where(active[i] > 0, p, FAR + 10.0 * i)
        pos = pos.at[i].set(p)
        placed_mask = placed_mask.at[i].set(active[i])
        return (pos, placed_mask), None

    init = (jnp.full((n, 2), FAR, jnp.float32), jnp.zeros(n))
    (pos, _), _ = jax.lax.scan(body, init, jnp.arange(n))
    return pos
