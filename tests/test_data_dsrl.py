"""DSRL-format HDF5 round trips, real-DSRL-shaped files, and one clear error per bad file."""

import os

import h5py
import numpy as np
import pytest

from safecdt_jax.data import (
    KEYS,
    DatasetError,
    load_dataset,
    make_dataset,
    write_dataset,
)
from safecdt_jax.data.dataset import to_flat

ARRAYS = ("observations", "next_observations", "actions", "rewards", "costs")


def toy_dataset():
    """4 episodes, horizon 6, lengths 6/3/5/1; episode 1 ends on a terminal."""
    rng = np.random.default_rng(0)
    n, t = 4, 6
    return make_dataset(
        rng.normal(size=(n, t, 3)),
        rng.uniform(-1, 1, size=(n, t, 2)),
        rng.random((n, t)),
        (rng.random((n, t)) < 0.4).astype(np.float32),
        [6, 3, 5, 1],
        terminals=[False, True, False, False],
        timeouts=[True, False, True, True],
        episode_info={"knob": np.array([0.1, 0.2, 0.3, 0.4]), "seed": np.arange(4)},
        attrs={"task": "CarGoal1", "collector_version": "0.1", "n": 3, "scale": 0.5},
    )


def test_round_trip_dataset(tmp_path):
    ds = toy_dataset()
    path = tmp_path / "d.hdf5"
    write_dataset(path, ds, attrs={"env_params": {"hazards": [1, 2]}})
    back = load_dataset(path)
    for k in (*ARRAYS, "lengths", "terminals", "timeouts", "return_offset", "cost_offset"):
        np.testing.assert_array_equal(getattr(back, k), getattr(ds, k), err_msg=k)
    assert back.observations.dtype == np.float32 and back.lengths.dtype == np.int32
    assert set(back.episode_info) == {"knob", "seed"}
    np.testing.assert_array_equal(back.episode_info["knob"], ds.episode_info["knob"])
    assert back.attrs["task"] == "CarGoal1" and back.attrs["n"] == 3 and back.attrs["scale"] == 0.5
    assert back.attrs["env_params"] == '{"hazards": [1, 2]}'  # dicts are stored as JSON
    assert [p.name for p in tmp_path.iterdir()] == ["d.hdf5"]  # no temporary file left


def test_round_trip_flat_and_episode_list(tmp_path):
    ds = toy_dataset()
    flat = to_flat(ds)
    write_dataset(tmp_path / "flat.hdf5", flat)
    with h5py.File(tmp_path / "flat.hdf5", "r") as f:
        assert set(f.keys()) == set(KEYS)
        for k in KEYS:
            np.testing.assert_array_equal(f[k][()], flat[k], err_msg=k)
    episodes = [
        {k: np.asarray(getattr(ds, k))[i, : ds.lengths[i]] for k in ARRAYS} for i in range(4)
    ]
    write_dataset(tmp_path / "list.hdf5", episodes)
    back = load_dataset(tmp_path / "list.hdf5")
    np.testing.assert_array_equal(back.lengths, [6, 3, 5, 1])
    np.testing.assert_array_equal(back.timeouts, [True] * 4)  # default: time-limit ends
    for k in ARRAYS:
        np.testing.assert_array_equal(getattr(back, k), getattr(ds, k), err_msg=k)


def test_episode_without_flags_is_split_on_write(tmp_path):
    # Episode 0 has neither flag; written flat it would merge with episode 1 unless marked.
    ds = make_dataset(
        np.ones((2, 3, 1)),
        np.ones((2, 3, 1)),
        np.ones((2, 3)),
        np.zeros((2, 3)),
        [2, 3],
        terminals=[False, False],
        timeouts=[False, True],
    )
    write_dataset(tmp_path / "d.hdf5", ds)
    np.testing.assert_array_equal(load_dataset(tmp_path / "d.hdf5").lengths, [2, 3])


def write_raw(path, n_rows=10, obs_dim=4, ends=(3, 9), **override):
    """A file as DSRL writes it: only the 7 flat keys, gzip, rewards/costs as N x 1, no attrs."""
    rng = np.random.default_rng(1)
    arrays = {
        "observations": rng.normal(size=(n_rows, obs_dim)).astype(np.float32),
        "next_observations": rng.normal(size=(n_rows, obs_dim)).astype(np.float32),
        "actions": rng.uniform(-1, 1, size=(n_rows, 2)).astype(np.float32),
        "rewards": rng.random((n_rows, 1)).astype(np.float32),
        "costs": (rng.random((n_rows, 1)) < 0.5).astype(np.float32),
        "terminals": np.zeros(n_rows, bool),
        "timeouts": np.zeros(n_rows, bool),
    }
    arrays["timeouts"][list(ends)] = True
    arrays.update(override)
    with h5py.File(path, "w") as f:
        for k, v in arrays.items():
            if v is not None:
                f.create_dataset(k, data=v, compression="gzip")
    return arrays


def test_real_dsrl_shaped_file_loads(tmp_path):
    path = tmp_path / "SafetyCarGoal1Gymnasium-v0-120-2.hdf5"
    raw = write_raw(path)
    ds = load_dataset(path, obs_dim=4, horizon=8)
    np.testing.assert_array_equal(ds.lengths, [4, 6])
    assert ds.observations.shape == (2, 8, 4) and ds.rewards.shape == (2, 8)
    np.testing.assert_array_equal(ds.observations[1, :6], raw["observations"][4:])
    np.testing.assert_array_equal(ds.rewards[0, :4], raw["rewards"][:4, 0])
    np.testing.assert_array_equal(ds.costs[1, :6], raw["costs"][4:, 0])
    assert not ds.observations[0, 4:].any() and not ds.rewards[1, 6:].any()  # zero padding
    assert dict(ds.attrs) == {} and ds.episode_info == {}


def test_trailing_rows_without_flag_form_an_episode(tmp_path):
    path = tmp_path / "d.hdf5"
    write_raw(path, ends=(3,))  # rows 4..9 have no terminal/timeout at the end
    ds = load_dataset(path)
    np.testing.assert_array_equal(ds.lengths, [4, 6])
    assert ds.horizon == 6  # the longest episode, when no horizon is given
    np.testing.assert_array_equal(ds.timeouts, [True, False])


def test_terminal_flags_as_floats_split_episodes(tmp_path):
    term = np.zeros(10, np.float32)
    term[1] = 1.0
    write_raw(tmp_path / "d.hdf5", terminals=term)
    ds = load_dataset(tmp_path / "d.hdf5")
    np.testing.assert_array_equal(ds.lengths, [2, 2, 6])
    np.testing.assert_array_equal(ds.terminals, [True, False, False])


BAD = {
    "missing_key": (dict(costs=None), {}, r"missing key\(s\) costs"),
    "rows_disagree": (
        dict(rewards=np.zeros((9, 1), np.float32)),
        {},
        r"disagree in row count.*rewards=9",
    ),
    "obs_dim": ({}, dict(obs_dim=5), r"observation size 4 does not match obs_dim=5"),
    "nan_reward": (
        dict(rewards=np.r_[np.zeros(9), np.nan][:, None]),
        {},
        r"key rewards.*non-finite",
    ),
    "inf_obs": (
        dict(observations=np.full((10, 4), np.inf, np.float32)),
        {},
        r"key observations.*non-finite",
    ),
    "too_long": ({}, dict(horizon=5), r"episode 1 has 6 steps, longer than horizon=5"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_file_gives_one_clear_error(tmp_path, case):
    override, kwargs, pattern = BAD[case]
    path = tmp_path / f"{case}.hdf5"
    write_raw(path, **override)
    with pytest.raises(DatasetError, match=pattern) as err:
        load_dataset(path, **kwargs)
    assert str(path) in str(err.value)
    assert isinstance(err.value, ValueError)


def test_missing_and_non_hdf5_files(tmp_path):
    with pytest.raises(DatasetError, match="file not found"):
        load_dataset(tmp_path / "nope.hdf5")
    text = tmp_path / "notes.hdf5"
    text.write_text("not an hdf5 file")
    with pytest.raises(DatasetError, match=r"notes\.hdf5: not an HDF5 file"):
        load_dataset(text)


def test_bad_episode_info_in_file(tmp_path):
    path = tmp_path / "d.hdf5"
    write_raw(path)
    with h5py.File(path, "a") as f:
        f.create_group("episode_info").create_dataset("knob", data=np.zeros(3))
    with pytest.raises(DatasetError, match=r"episode_info\['knob'\].*2 episodes"):
        load_dataset(path)


def test_failed_write_keeps_old_file_and_leaves_no_temp(tmp_path):
    path = tmp_path / "d.hdf5"
    write_dataset(path, toy_dataset())
    before = path.read_bytes()
    with pytest.raises(DatasetError, match=r"episode_info\['knob'\]"):
        write_dataset(path, toy_dataset(), episode_info={"knob": np.zeros(7)})
    with pytest.raises(DatasetError, match=r"key actions.*non-finite"):
        bad = to_flat(toy_dataset())
        bad["actions"][0, 0] = np.nan
        write_dataset(path, bad)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["d.hdf5"]


def test_relabelled_dataset_refuses_to_write(tmp_path):
    import dataclasses

    ds = dataclasses.replace(toy_dataset(), cost_offset=np.array([0, 1, 0, 0], np.float32))
    with pytest.raises(DatasetError, match="non-zero offsets"):
        write_dataset(tmp_path / "d.hdf5", ds)
    assert not (tmp_path / "d.hdf5").exists()


def test_bad_episode_list_is_refused(tmp_path):
    episode = {k: np.zeros((3, 2)) for k in ("observations", "next_observations", "actions")}
    with pytest.raises(DatasetError, match=r"episode 0 is missing key\(s\) rewards, costs"):
        write_dataset(tmp_path / "d.hdf5", [episode])
    assert not (tmp_path / "d.hdf5").exists()


def test_loaded_dataset_is_a_jit_argument(tmp_path):
    import jax

    from safecdt_jax.data import returns_to_go

    write_dataset(tmp_path / "d.hdf5", toy_dataset(), attrs={"env_params": {"a": [1, 2]}})
    ds = load_dataset(tmp_path / "d.hdf5", horizon=8)
    on_device = jax.device_put(ds)
    assert on_device.attrs == ds.attrs and hash(on_device.attrs) == hash(ds.attrs)
    rtg = jax.jit(returns_to_go)(on_device)
    assert rtg.shape == (4, 8)
    want = np.cumsum(ds.rewards[:, ::-1], axis=1)[:, ::-1]  # zero padding: plain suffix sums
    np.testing.assert_allclose(
        rtg, np.where(np.arange(8) < ds.lengths[:, None], want, 0), rtol=1e-6
    )
