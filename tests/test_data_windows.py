"""Suffix sums, trajectory weights and K-step windows on hand-made episodes with known values."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.data import (
    costs_to_go,
    make_dataset,
    returns_to_go,
    sample_windows,
    suffix_sums,
    trajectory_weights,
)

sample_jit = jax.jit(sample_windows, static_argnames=("batch", "K", "constant"))


def hand_data():
    """Two episodes, horizon 5. Observation of episode i at step t is (100 i + t, -t)."""
    t = np.arange(5)
    obs = np.stack([np.stack([100 * i + t, -t], -1) for i in range(2)]).astype(np.float32)
    actions = obs[..., :1] + 0.5
    rewards = np.array([[1, 2, 3, 0, 0], [1, 1, 1, 1, 1]], np.float32)
    costs = np.array([[0, 1, 1, 0, 0], [1, 0, 0, 0, 1]], np.float32)
    return make_dataset(obs, actions, rewards, costs, [3, 5])


def test_suffix_sums_ignore_values_past_length():
    values = jnp.array([[1.0, 2.0, 3.0, 9.0, 9.0], [4.0, 5.0, 6.0, 7.0, 8.0]])
    np.testing.assert_array_equal(
        suffix_sums(values, jnp.array([3, 0])), [[6, 5, 3, 0, 0], [0, 0, 0, 0, 0]]
    )


def test_returns_and_costs_to_go_known_values():
    ds = hand_data()
    np.testing.assert_array_equal(returns_to_go(ds), [[6, 5, 3, 0, 0], [5, 4, 3, 2, 1]])
    np.testing.assert_array_equal(costs_to_go(ds), [[2, 2, 1, 0, 0], [2, 1, 1, 1, 1]])
    shifted = dataclasses.replace(
        ds,
        return_offset=np.array([10.0, 0.0], np.float32),
        cost_offset=np.array([0.0, 3.0], np.float32),
    )
    np.testing.assert_array_equal(returns_to_go(shifted), [[16, 15, 13, 0, 0], [5, 4, 3, 2, 1]])
    np.testing.assert_array_equal(costs_to_go(shifted), [[2, 2, 1, 0, 0], [5, 4, 4, 4, 4]])


# Episode 0 (length 3), K = 4, reward_scale 0.1: the expected window for each possible start.
EXPECTED = {
    0: dict(
        t=[0, 1, 2, 3],
        mask=[1, 1, 1, 0],
        rtg=[0.6, 0.5, 0.3, 0],
        ctg=[2, 2, 1, 0],
        cost=[0, 1, 1, 0],
        obs=[0, 1, 2, 0],
    ),
    1: dict(
        t=[1, 2, 3, 4],
        mask=[1, 1, 0, 0],
        rtg=[0.5, 0.3, 0, 0],
        ctg=[2, 1, 0, 0],
        cost=[1, 1, 0, 0],
        obs=[1, 2, 0, 0],
    ),
    2: dict(
        t=[2, 3, 4, 5],
        mask=[1, 0, 0, 0],
        rtg=[0.3, 0, 0, 0],
        ctg=[1, 0, 0, 0],
        cost=[1, 0, 0, 0],
        obs=[2, 0, 0, 0],
    ),
}


def test_windows_match_hand_computed_values():
    w = sample_jit(jax.random.key(0), hand_data(), batch=64, K=4, weights=jnp.array([1.0, 0.0]))
    assert w.states.shape == (64, 4, 2) and w.actions.shape == (64, 4, 1)
    assert w.timesteps.dtype == jnp.int32 and w.mask.dtype == jnp.float32
    np.testing.assert_array_equal(w.episode_index, 0)
    assert set(np.asarray(w.start).tolist()) == {0, 1, 2}  # uniform over [0, len-1]
    for b in range(64):
        e = EXPECTED[int(w.start[b])]
        np.testing.assert_array_equal(w.timesteps[b], e["t"])  # counts on past the end (5)
        np.testing.assert_array_equal(w.mask[b], e["mask"])
        np.testing.assert_allclose(w.returns_to_go[b], e["rtg"], rtol=1e-6)
        np.testing.assert_array_equal(w.costs_to_go[b], e["ctg"])
        np.testing.assert_array_equal(w.costs[b], e["cost"])
        np.testing.assert_array_equal(w.states[b, :, 0], e["obs"])
        want_actions = np.add(e["obs"], np.multiply(0.5, e["mask"]))
        np.testing.assert_array_equal(w.actions[b, :, 0], want_actions)


def test_constant_windows_carry_the_episode_t0_tokens_at_every_valid_step():
    data = dataclasses.replace(hand_data(), cost_offset=np.array([4.0, 0.0], np.float32))
    w = sample_jit(jax.random.key(1), data, batch=64, K=4, reward_scale=0.1, cost_scale=0.5,
                   constant=True)
    plain = sample_jit(jax.random.key(1), data, batch=64, K=4, reward_scale=0.1,
                       cost_scale=0.5)
    t0 = {0: (0.6, 3.0), 1: (0.5, 1.0)}  # (RTG, (CTG + offset)) * scales at t = 0
    assert set(np.asarray(w.episode_index).tolist()) == {0, 1}
    for b in range(64):
        rtg, ctg = t0[int(w.episode_index[b])]
        np.testing.assert_allclose(w.returns_to_go[b], rtg * w.mask[b], rtol=1e-6)
        np.testing.assert_allclose(w.costs_to_go[b], ctg * w.mask[b], rtol=1e-6)
    # Only the tokens differ: the same key draws the same windows.
    for name in ("states", "actions", "costs", "timesteps", "mask", "start"):
        np.testing.assert_array_equal(getattr(w, name), getattr(plain, name), err_msg=name)
    assert not np.array_equal(w.costs_to_go, plain.costs_to_go)


def test_padding_mask_and_scales_on_full_length_episode():
    w = sample_jit(
        jax.random.key(1),
        hand_data(),
        batch=256,
        K=4,
        weights=jnp.array([0.0, 1.0]),
        reward_scale=1.0,
        cost_scale=2.0,
    )
    start = np.asarray(w.start)
    np.testing.assert_array_equal(np.asarray(w.mask).sum(1), np.minimum(4, 5 - start))
    np.testing.assert_array_equal(w.timesteps, start[:, None] + np.arange(4))
    t = np.minimum(start[:, None] + np.arange(4), 4)
    valid = np.asarray(w.mask) > 0
    np.testing.assert_array_equal(w.returns_to_go, np.where(valid, 5.0 - t, 0))
    ctg = np.array([2, 1, 1, 1, 1])[t] * 2.0
    np.testing.assert_array_equal(w.costs_to_go, np.where(valid, ctg, 0))
    np.testing.assert_array_equal(np.asarray(w.states)[..., 0], np.where(valid, 100 + t, 0))


def test_trajectory_weights_formula():
    costs = np.zeros((4, 5), np.float32)
    costs[:, 0] = [10, 75, 70, 30]
    ds = make_dataset(
        np.zeros((4, 5, 1)), np.zeros((4, 5, 1)), np.zeros((4, 5)), costs, [5, 5, 5, 5]
    )
    np.testing.assert_allclose(trajectory_weights(ds), [0.6, 0, 0, 0.4], rtol=1e-6)
    np.testing.assert_allclose(trajectory_weights(ds, c0=50.0), [40 / 60, 0, 0, 20 / 60], rtol=1e-6)
    # Relabelled cost-to-go counts: an offset of 25 on episode 3 makes its C = 55.
    shifted = dataclasses.replace(ds, cost_offset=np.array([0, 0, 0, 25], np.float32))
    np.testing.assert_allclose(trajectory_weights(shifted), [60 / 75, 0, 0, 15 / 75], rtol=1e-6)
    with pytest.raises(ValueError, match=r"all 4 episodes have zero weight.*c0=5"):
        trajectory_weights(ds, c0=5.0)


def test_sampler_follows_weights():
    ds = hand_data()
    ds = dataclasses.replace(
        ds,
        **{
            k: np.concatenate([getattr(ds, k)] * 2)
            for k in ("observations", "actions", "rewards", "costs", "lengths")
        },
    )  # 4 episodes, lengths 3, 5, 3, 5
    weights = jnp.array([0.5, 0.0, 0.3, 0.2])
    w = sample_jit(jax.random.key(2), ds, batch=8192, K=2, weights=weights)
    freq = np.bincount(np.asarray(w.episode_index), minlength=4) / 8192
    assert freq[1] == 0.0  # zero weight: never drawn
    np.testing.assert_allclose(freq, weights, atol=0.025)
    # weights=None: uniform over valid positions, i.e. episode frequency proportional to length.
    w = sample_jit(jax.random.key(3), ds, batch=8192, K=2)
    freq = np.bincount(np.asarray(w.episode_index), minlength=4) / 8192
    np.testing.assert_allclose(freq, np.array([3, 5, 3, 5]) / 16, atol=0.025)


def test_jit_equals_no_jit_and_same_key_same_bits():
    ds, key = hand_data(), jax.random.key(7)
    weights = jnp.array([0.4, 0.6])
    a = sample_windows(key, ds, 32, 4, weights)
    b = sample_jit(key, ds, batch=32, K=4, weights=weights)
    c = sample_jit(key, ds, batch=32, K=4, weights=weights)
    d = sample_jit(jax.random.key(8), ds, batch=32, K=4, weights=weights)
    for name, x, y, z in zip(a._fields, a, b, c, strict=True):
        np.testing.assert_array_equal(x, y, err_msg=name)
        np.testing.assert_array_equal(y, z, err_msg=name)
    assert not np.array_equal(b.start, d.start) or not np.array_equal(
        b.episode_index, d.episode_index
    )


def test_an_episode_view_with_padding_draws_the_copied_data_windows():
    """Episodes as a view (`source`: the row each reads) with trailing empty padding give the
    windows of the same episodes copied out, bit for bit (what `pretrain.seeds` relies on)."""
    from typing import NamedTuple

    class View(NamedTuple):
        observations: np.ndarray
        actions: np.ndarray
        rewards: np.ndarray
        costs: np.ndarray
        lengths: np.ndarray
        return_offset: np.ndarray
        cost_offset: np.ndarray
        source: np.ndarray

    ds = hand_data()
    order = np.array([1, 0, 1])  # episode 1 twice (a relabelled copy), shifted labels
    offsets = (np.array([0.0, 0.0, 5.0], np.float32), np.array([0.0, 0.0, 2.0], np.float32))
    copied = dataclasses.replace(
        ds, **{k: getattr(ds, k)[order] for k in ("observations", "actions", "rewards",
                                                   "costs", "lengths")},
        return_offset=offsets[0], cost_offset=offsets[1])
    pad = lambda x: np.concatenate([x, np.zeros(2, x.dtype)])  # two empty episodes
    view = View(ds.observations, ds.actions, ds.rewards, ds.costs,
                pad(np.asarray(ds.lengths)[order]), pad(offsets[0]), pad(offsets[1]),
                pad(order.astype(np.int32)))
    weights = np.array([0.5, 0.2, 0.3], np.float32)
    a = sample_jit(jax.random.key(4), copied, batch=64, K=3, weights=weights)
    b = sample_jit(jax.random.key(4), view, batch=64, K=3, weights=pad(weights))
    for name, x, y in zip(a._fields, a, b, strict=True):
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert set(np.asarray(b.episode_index).tolist()) == {0, 1, 2}  # never the padding
