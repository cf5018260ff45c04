"""Pretraining vmapped over seeds equals the single runs, and its checkpoints read as theirs."""

import dataclasses

import jax
import numpy as np
import pytest
from test_pretrain import CFG, OPTIM, TASK, synthetic_dataset

from safecdt_jax.data import write_dataset
from safecdt_jax.pretrain import checkpoint_steps, load_checkpoint, pretrain, read_meta
from safecdt_jax.pretrain.loop import labelled, prepare_data
from safecdt_jax.pretrain.seeds import prepare_seeds, pretrain_seeds

SEEDS = (0, 1)
# Every grid-filtered episode gets a relabelled copy, so that the views are exercised.
RUN = CFG.replace(steps=40, checkpoint_every=20, relabel_percent=1.0)


def grouped_dataset():
    """24 episodes in 6 groups of 4 equal (return, cost) totals: the relabelling's grid keeps
    bins of at least 3, so every episode survives it and gets a copy."""
    data = synthetic_dataset()
    group = np.arange(24)[:, None] // 4
    rewards = np.broadcast_to(0.1 * (group + 1), data.rewards.shape).astype(np.float32)
    costs = (np.arange(data.rewards.shape[1])[None, :] < group).astype(np.float32)
    return dataclasses.replace(data, rewards=rewards, costs=costs)


@pytest.fixture(scope="module")
def data_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "synthetic.hdf5"
    write_dataset(path, grouped_dataset())
    return path


@pytest.fixture(scope="module")
def vmapped(data_file, tmp_path_factory):
    root = tmp_path_factory.mktemp("seeds")
    return pretrain_seeds(data_file, SEEDS, [root / f"s{k}" for k in SEEDS], preset="tiny",
                          config=RUN, optim=OPTIM, progress=False)


def test_each_seed_draws_its_single_runs_episode_list():
    data = labelled(grouped_dataset(), RUN)
    arrays, weights, n_copies = prepare_seeds(data, RUN, SEEDS)
    assert arrays.observations.shape[0] == data.n_episodes  # step arrays held once
    for i, seed in enumerate(SEEDS):
        single, w, m = prepare_data(data, RUN.replace(seed=seed))
        assert m == n_copies[i] == data.n_episodes
        n = single.lengths.shape[0]
        np.testing.assert_array_equal(weights[i, :n], w)
        assert np.all(weights[i, n:] == 0) and np.all(arrays.lengths[i, n:] == 0)
        for name in ("lengths", "return_offset", "cost_offset"):
            np.testing.assert_array_equal(getattr(arrays, name)[i, :n], getattr(single, name))
        # Each copy reads the steps of the episode it copies.
        rows = np.asarray(arrays.source[i, :n])
        np.testing.assert_array_equal(np.asarray(arrays.observations)[rows],
                                      np.asarray(single.observations))


def test_vmapped_seeds_equal_single_runs(vmapped, data_file, tmp_path):
    for k, run in zip(SEEDS, vmapped, strict=True):
        one = pretrain(data_file, tmp_path / f"one{k}", preset="tiny",
                       config=RUN.replace(seed=k), optim=OPTIM, progress=False)
        # The same windows and dropout; the batched matmuls sum in another order.
        np.testing.assert_allclose(run.history.metrics["loss"], one.history.metrics["loss"],
                                   rtol=1e-4)
        for a, b in zip(jax.tree.leaves(run.state.params), jax.tree.leaves(one.state.params),
                        strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-3, atol=1e-5)
        saved, single = read_meta(run.path), read_meta(one.path)
        for key in ("model", "optim", "pretrain", "dataset", "step", "finished"):
            assert saved[key] == single[key], key
        assert checkpoint_steps(run.path) == [20, 40]
    a, b = (jax.tree.leaves(r.state.params) for r in vmapped)
    assert not np.allclose(np.asarray(a[0]), np.asarray(b[0]))  # the seeds differ
    load_checkpoint(vmapped[1].path)  # reads as any checkpoint


def test_resumed_seeds_continue_with_the_same_bits(vmapped, data_file, tmp_path):
    """Seed 0 stopped at update 20, seed 1 never started: one call brings both to 40, each as
    the uninterrupted two-seed run (to float rounding: seed 0's first 20 updates ran in a
    one-seed program, whose batched matmuls sum in another order; a restart from scratch or
    a lost checkpoint would differ by the whole training), and seed 0's history goes on from
    its checkpoint's."""
    outs = [tmp_path / f"s{k}" for k in SEEDS]
    pretrain_seeds(data_file, SEEDS[:1], outs[:1], preset="tiny", config=RUN.replace(steps=20),
                   optim=OPTIM, progress=False)
    assert checkpoint_steps(outs[0]) == [20] and not outs[1].exists()
    stamp = (outs[0] / "20").stat().st_mtime_ns
    resumed = pretrain_seeds(data_file, SEEDS, outs, preset="tiny", config=RUN, optim=OPTIM,
                             progress=False)
    # Seed 0 went on from its checkpoint (a fresh start would have written step 20 again).
    assert (outs[0] / "20").stat().st_mtime_ns == stamp
    assert checkpoint_steps(outs[0]) == checkpoint_steps(outs[1]) == [20, 40]
    for r, whole in zip(resumed, vmapped, strict=True):
        assert r.history.step == whole.history.step
        for a, b in zip(jax.tree.leaves(r.state.params), jax.tree.leaves(whole.state.params),
                        strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)


def test_bad_seed_lists_and_foreign_checkpoints_are_clear_errors(vmapped, data_file):
    with pytest.raises(ValueError, match="distinct seeds"):
        pretrain_seeds(data_file, [1, 1], preset="tiny", config=RUN)
    from safecdt_jax.pretrain import CheckpointError

    with pytest.raises(CheckpointError, match=r"pretrain\.batch_size"):
        pretrain_seeds(data_file, SEEDS, [r.path for r in vmapped], preset="tiny",
                       config=RUN.replace(batch_size=8), optim=OPTIM, progress=False)
    assert read_meta(vmapped[0].path)["task"] == TASK  # untouched by the refused call
