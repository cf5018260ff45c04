"""Several cooperating processes: settings, bad input, and a 2-process deployment that equals
one process's over two devices, written once."""

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from process_helpers import free_port, run_peers
from typer.testing import CliRunner

from safecdt_jax.distributed import Cluster, cluster_from

ROOT = Path(__file__).resolve().parents[1]
# 8 seeds x 3 episodes of 20 steps, LoRA after every episode, the scheduler every episode.
SETTINGS = dict(horizon=20, lora_steps=2, lora_batch=4, window=2, stage_len=1, lambda_warmup=1,
                lora_in_turn=True)


def test_settings_come_from_flags_then_environment():
    env = {"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234", "JAX_NUM_PROCESSES": "4",
           "JAX_PROCESS_ID": "3"}
    assert cluster_from(environ=env) == Cluster("10.0.0.1:1234", 4, 3)
    assert cluster_from(process_id=1, environ=env) == Cluster("10.0.0.1:1234", 4, 1)
    assert cluster_from(environ={}) == Cluster(None, 1, 0)


@pytest.mark.parametrize("kwargs, message", [
    (dict(coordinator="h:1", num_processes=2, process_id=2), "process id 2 out of range"),
    (dict(coordinator="h:1", num_processes=2), "need this process's id"),
    (dict(num_processes=2, process_id=0), "need a coordinator address"),
    (dict(coordinator="nohostport", num_processes=2, process_id=0), "HOST:PORT"),
    (dict(process_id=1), "without the number of processes"),
])
def test_bad_settings_are_one_clear_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        cluster_from(**kwargs, environ={})


def test_the_cli_reports_a_process_id_out_of_range_in_one_line(tiny_run):
    from safecdt_jax.cli import app

    _, ckpt, _ = tiny_run
    result = CliRunner().invoke(app, ["deploy", "--ckpt", str(ckpt), "--pair", "PC1-PC2",
                                      "--coordinator", "127.0.0.1:1", "--num-processes", "2",
                                      "--process-id", "5"])
    assert result.exit_code == 1
    assert result.output.strip().splitlines() == [
        "error: process id 5 out of range for 2 process(es): it must be in 0..1"]


def _deploy_command(ckpt, out) -> list[str]:
    sets = [arg for k, v in SETTINGS.items() for arg in ("--set", f"{k}={v}")]
    return [sys.executable, "-c", "from safecdt_jax.cli import main; main()", "deploy",
            "--ckpt", str(ckpt), "--pair", "PC1-PC2", "--variant", "safe_cdt", "--budget", "5",
            "--seeds", "8", "--episodes", "3", "--out", str(out), *sets]


@pytest.mark.slow
def test_two_processes_deploy_like_one_and_only_process_0_writes(tiny_run, tmp_path):
    _, ckpt, _ = tiny_run
    address = f"127.0.0.1:{free_port()}"
    base = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # one CPU device each
    base.update(JAX_PLATFORMS="cpu", SAFECDT_CACHE=str(tmp_path / "cache"))
    # Process 0 is told by flags, process 1 by JAX's environment variables.
    commands = [[*_deploy_command(ckpt, tmp_path / "out0"), "--coordinator", address,
                 "--num-processes", "2", "--process-id", "0"],
                _deploy_command(ckpt, tmp_path / "out1")]
    envs = [base, dict(base, JAX_COORDINATOR_ADDRESS=address, JAX_NUM_PROCESSES="2",
                       JAX_PROCESS_ID="1")]
    done = run_peers(commands, envs, tmp_path, ROOT, timeout=240)
    for rank, (code, log) in enumerate(done):
        assert code == 0, f"process {rank}:\n{log[-3000:]}"
    logs = [log for _, log in done]
    assert "process 1: done; process 0 writes" in logs[1]
    assert not (tmp_path / "out1").exists()  # process 1 wrote nothing
    gathered = json.loads((tmp_path / "out0" / "results.json").read_text())

    # The same sweep in one process over two CPU devices: each device runs the same program on
    # the same 4 seeds as each process did, so the metrics are the same bits. (Not against one
    # device's 8 seeds: XLA's CPU kernels may sum a batch of 8 in another order than a batch of
    # 4, so on some CPUs, a 2-core AMD EPYC without AVX-512 among them, the returns then differ
    # by ~1e-4 after a few episodes.)
    two_devices = dict(base, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    (code, log), = run_peers([_deploy_command(ckpt, tmp_path / "alone")], [two_devices],
                             tmp_path, ROOT, timeout=240)
    assert code == 0, log[-3000:]
    alone = json.loads((tmp_path / "alone" / "results.json").read_text())
    assert gathered["seeds"] == alone["seeds"] == 8
    for name, values in alone["runs"][0]["metrics"].items():
        got = np.asarray(gathered["runs"][0]["metrics"][name])
        assert got.shape == (8, 3), name
        np.testing.assert_array_equal(got, np.asarray(values), err_msg=name)
    assert np.ptp(np.asarray(alone["runs"][0]["metrics"]["return"])) > 0  # seeds differ
