"""The fixed-size episode buffer: pure adds under jit, wrap-around, and window sampling on it."""

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.data import buffer_add, buffer_init, buffer_size, sample_windows, suffix_sums

T, OBS, ACT = 5, 2, 1


def episode(i):
    """Episode i (int or traced); non-zero past any length, which the buffer must zero out."""
    t = jnp.arange(T, dtype=jnp.float32)
    return {
        "observations": jnp.stack([10.0 * i + t, -t], -1),
        "actions": (10.0 * i + t)[:, None],
        "rewards": jnp.ones(T) * (i + 1),
        "costs": jnp.where(t % 2 == 0, 1.0, 0.0),
    }


@jax.jit
def fill(buf, lengths):
    """Add episodes 0..len(lengths)-1 with a scan: the deployment loop's shape of use."""

    def step(b, x):
        i, length = x
        return buffer_add(b, episode(i), length), None

    idx = jnp.arange(lengths.shape[0], dtype=jnp.float32)
    return jax.lax.scan(step, buf, (idx, lengths))[0]


def test_add_under_jit_writes_slots_and_zero_pads():
    buf = fill(buffer_init(4, T, OBS, ACT), jnp.array([4, 2, 5], jnp.int32))
    np.testing.assert_array_equal(buf.lengths, [4, 2, 5, 0])
    assert int(buf.count) == 3 and int(buffer_size(buf)) == 3
    np.testing.assert_array_equal(buf.observations[1, :, 0], [10, 11, 0, 0, 0])
    np.testing.assert_array_equal(buf.rewards[1], [2, 2, 0, 0, 0])
    np.testing.assert_array_equal(buf.costs[0], [1, 0, 1, 0, 0])
    np.testing.assert_array_equal(buf.actions[2, :, 0], [20, 21, 22, 23, 24])
    assert not np.any(buf.observations[3])  # untouched slot stays empty


def test_full_buffer_wraps_over_the_oldest_episode():
    buf = buffer_init(2, T, OBS, ACT)
    add = jax.jit(buffer_add)
    for i, length in enumerate([3, 4, 2]):
        buf = add(buf, episode(i), length)
    np.testing.assert_array_equal(buf.lengths, [2, 4])  # slot 0 now holds episode 2
    np.testing.assert_array_equal(buf.observations[0, :, 0], [20, 21, 0, 0, 0])
    assert int(buf.count) == 3 and int(buffer_size(buf)) == 2


def test_sampling_from_buffer_under_jit():
    buf = fill(buffer_init(6, T, OBS, ACT), jnp.array([4, 2, 5], jnp.int32))
    sample = jax.jit(sample_windows, static_argnames=("batch", "K"))
    w = sample(jax.random.key(0), buf, batch=4096, K=3)
    ep, start = np.asarray(w.episode_index), np.asarray(w.start)
    assert set(ep.tolist()) == {0, 1, 2}  # empty slots 3..5 are never drawn
    np.testing.assert_array_equal(w.mask[:, 0], 1.0)  # every window starts on a real step
    assert np.all(start < np.array([4, 2, 5])[ep])
    # Uniform over the 11 valid (episode, step) positions.
    pos = np.bincount(np.array([0, 4, 6])[ep] + start, minlength=11) / 4096
    np.testing.assert_allclose(pos, 1 / 11, atol=0.02)
    rtg = np.asarray(suffix_sums(buf.rewards, buf.lengths))
    ctg = np.asarray(suffix_sums(buf.costs, buf.lengths))
    t = np.minimum(np.asarray(w.timesteps), T - 1)
    mask = np.asarray(w.mask) > 0
    np.testing.assert_allclose(
        w.returns_to_go, np.where(mask, rtg[ep[:, None], t] * 0.1, 0), rtol=1e-6
    )
    np.testing.assert_array_equal(w.costs_to_go, np.where(mask, ctg[ep[:, None], t], 0))
    np.testing.assert_array_equal(
        w.states[..., 0], np.where(mask, 10 * ep[:, None] + np.asarray(w.timesteps), 0)
    )
    again = sample(jax.random.key(0), buf, batch=4096, K=3)
    np.testing.assert_array_equal(again.states, w.states)


def test_empty_buffer_gives_fully_masked_windows():
    w = sample_windows(jax.random.key(0), buffer_init(3, T, OBS, ACT), 8, 3)
    assert not np.any(w.mask) and not np.any(w.states)
