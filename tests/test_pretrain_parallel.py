"""Data-parallel pretraining: the batch sharded over 2 (forced CPU) devices equals 1 device."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from data_helpers import expert_episodes
from process_helpers import free_port, run_peers

from safecdt_jax.model import CDTConfig, OptimConfig, init_train_state
from safecdt_jax.pretrain import default_pretrain
from safecdt_jax.pretrain.loop import make_train_chunk, prepare_data, stream_key, train

ROOT = Path(__file__).resolve().parents[1]
# 50 updates of 8 windows, in one process with `sys.argv[1]` devices listed ("all" or the
# default single-device program); prints the params, the curve and facts about the program.
_RUN = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    from data_helpers import expert_episodes
    from safecdt_jax.model import CDTConfig, OptimConfig, init_train_state
    from safecdt_jax.pretrain import default_pretrain
    from safecdt_jax.pretrain.loop import make_train_chunk, prepare_data, stream_key, train

    from safecdt_jax.distributed import Cluster, initialize, local_copy

    if sys.argv[1] == "cluster":  # argv: cluster ADDRESS PROCESS_ID, 2 processes
        initialize(Cluster(sys.argv[2], 2, int(sys.argv[3])))
    data = expert_episodes()
    cfg = default_pretrain("tiny", steps=50, chunk=25, batch_size=8)
    model = CDTConfig.preset("tiny", data.observations.shape[-1], data.actions.shape[-1], 20)
    optim = OptimConfig()
    arrays, weights, _ = prepare_data(data, cfg)
    state = init_train_state(stream_key(0, "init"), model, optim)
    devices = jax.devices() if sys.argv[1] in ("all", "cluster") else None
    state, history = train(state, arrays, weights, model, optim, cfg, progress=False,
                           devices=devices)
    if sys.argv[1] == "cluster":  # this process's copy of the replicated state
        print(json.dumps({"devices": len(state.step.sharding.device_set),
                          "params": [np.asarray(x).tolist()
                                     for x in jax.tree.leaves(local_copy(state.params))],
                          "loss": history.metrics["loss"]}))
        sys.exit(0)
    mesh = jax.sharding.Mesh(np.asarray(jax.devices()), ("data",))
    chunk = make_train_chunk(model, optim, cfg, mesh=mesh)
    hlo = chunk.lower(state, jax.random.key(0), arrays, weights, 50).compile().as_text()
    try:
        make_train_chunk(model, optim, cfg.replace(batch_size=7), mesh=mesh)
        odd = ""
    except ValueError as e:
        odd = str(e)
    print(json.dumps({"devices": len(state.step.sharding.device_set),
                      "params": [np.asarray(x).tolist() for x in jax.tree.leaves(state.params)],
                      "loss": history.metrics["loss"], "all_reduce": "all-reduce" in hlo,
                      "odd_batch": odd}))
""")


def _train(devices: int, which: str) -> dict:
    env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}",
               JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT / "tests"))
    proc = subprocess.run([sys.executable, "-c", _RUN, which], capture_output=True, text=True,
                          env=env, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _train_two_processes(folder: Path) -> list[dict]:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # one CPU device each
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT / "tests"))
    address = f"127.0.0.1:{free_port()}"
    commands = [[sys.executable, "-c", _RUN, "cluster", address, str(rank)] for rank in (0, 1)]
    done = run_peers(commands, [env, env], folder, ROOT, timeout=300)
    for rank, (code, text) in enumerate(done):
        assert code == 0, f"process {rank}:\n{text[-3000:]}"
    return [json.loads(text.strip().splitlines()[-1]) for _, text in done]


@pytest.mark.slow
def test_two_processes_train_like_one_device_and_agree(tmp_path):
    ranks = _train_two_processes(tmp_path)
    one = _train(1, "default")
    assert [r["devices"] for r in ranks] == [2, 2]  # one global mesh over both processes
    for a, b in zip(ranks[0]["params"], ranks[1]["params"], strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # replicated state
    np.testing.assert_allclose(ranks[0]["loss"], one["loss"], rtol=1e-5)
    for a, b in zip(ranks[0]["params"], one["params"], strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)


def _tiny():
    data = expert_episodes()
    model = CDTConfig.preset("tiny", data.observations.shape[-1], data.actions.shape[-1], 20)
    return data, model, init_train_state(stream_key(0, "init"), model, OptimConfig())


@pytest.mark.slow
def test_two_devices_train_like_one_up_to_summation_order():
    two = _train(2, "all")
    assert two["devices"] == 2 and two["all_reduce"]  # sharded batch, gradient all-reduced
    assert "multiple of the device count (2)" in two["odd_batch"]
    one = _train(1, "default")
    assert one["devices"] == 1
    # The same windows and dropout draws; only the order of the gradient sums differs.
    np.testing.assert_allclose(two["loss"], one["loss"], rtol=1e-5)
    for a, b in zip(two["params"], one["params"], strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    initial = jax.tree.leaves(_tiny()[2].params)
    assert not all(np.array_equal(np.asarray(a), np.asarray(b))  # it did train
                   for a, b in zip(one["params"], initial, strict=True))


def test_one_listed_device_is_the_default_program_bit_for_bit():
    data, model, state = _tiny()
    cfg = default_pretrain("tiny", steps=4, chunk=2, batch_size=4)
    arrays, weights, _ = prepare_data(data, cfg)
    runs = [train(state, arrays, weights, model, OptimConfig(), cfg, progress=False,
                  devices=devices)[0] for devices in (None, jax.devices()[:1])]
    for a, b in zip(*(jax.tree.leaves(r.params) for r in runs), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert make_train_chunk(model, OptimConfig(), cfg) is make_train_chunk(
        model, OptimConfig(), cfg, mesh=None)


@pytest.mark.slow
def test_cli_data_parallel_flag_trains_like_one_device(tmp_path):
    """`pretrain --data-parallel` on 2 devices writes the checkpoint one device writes, up to
    the order of the gradient sums; `--num-processes 2` without the flag is refused."""
    from data_helpers import write_expert_episodes
    from typer.testing import CliRunner

    from safecdt_jax.cli import app
    from safecdt_jax.pretrain.checkpoint import load_checkpoint

    data = write_expert_episodes(tmp_path / "d.hdf5")
    args = ["pretrain", "--data", str(data), "--preset", "tiny", "--steps", "20", "--batch", "8"]
    run = ("import sys; from safecdt_jax.cli import main; "
           f"sys.argv = ['safecdt-jax', *{args!r}, '--out', {str(tmp_path / 'two')!r}, "
           "'--data-parallel']; main()")
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", run], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "20 updates" in proc.stdout and "data-parallel over 2 devices of 1" in proc.stdout
    one = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "one")])
    assert one.exit_code == 0, one.output
    params = [jax.tree.leaves(load_checkpoint(tmp_path / n).params) for n in ("two", "one")]
    for a, b in zip(*params, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    refused = CliRunner().invoke(app, [*args, "--num-processes", "2"])
    assert refused.exit_code == 1 and "add --data-parallel" in refused.output
