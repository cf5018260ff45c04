"""Launching cooperating test processes on the loopback interface."""

import socket
import subprocess
from pathlib import Path


def free_port() -> int:
    """A TCP port on 127.0.0.1 that is free now (for a coordinator address)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_peers(commands: list[list[str]], envs: list[dict], folder: Path, cwd: Path,
              timeout: float) -> list[tuple[int, str]]:
    """Starts every command at once, each logging stdout and stderr to a file in `folder`
    (not a pipe: a peer blocked on a full pipe would stall the collectives of the others),
    waits up to `timeout` seconds for each, kills any still running, and returns each one's
    (exit code, log text)."""
    logs = [folder / f"rank{rank}.log" for rank in range(len(commands))]
    procs = []
    for command, env, log in zip(commands, envs, logs, strict=True):
        with open(log, "w") as out:  # the child keeps its own copy of the descriptor
            procs.append(subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT,
                                          env=env, cwd=cwd))
    try:
        for p in procs:
            p.wait(timeout=timeout)
    finally:  # a hung peer must not outlive the test
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return [(p.returncode, log.read_text()) for p, log in zip(procs, logs, strict=True)]
