"""Seeds x processes: one deployment sweep shared by N cooperating processes on one machine.

    python -m benchmarks.processes --ckpt ~/.cache/safecdt-jax/checkpoints/CarGoal1-cpu
        [--pair CG1-CG2] [--seeds 4,8,16] [--processes 1,2] [--episodes 5] [--horizon 200]
        [--repeats 2]

Each (processes N, seeds S) point runs `safecdt-jax deploy` (Safe-CDT) `--repeats` times,
N copies at once on the loopback interface, copy i pinned to core i (`taskset`) when N > 1,
and reports process 0's `timing.deploy_s` (the sweep call: compile on a cache miss, then the
episodes) of every repeat, and the wall time of the whole command (interpreter start, data
and checkpoint loading included). With N = 1 the one process uses every core (XLA's threads).
The seeds are padded to a multiple of N (the padding computed and dropped). Writes
benchmarks/results/processes.{json,md}.
"""

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import machine, markdown_table, median, write_json, write_markdown

RESULTS = Path(__file__).parent / "results"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _deploy(args, n: int, seeds: int, folder: Path) -> tuple[float, float]:
    """(process 0's deploy_s, the command's wall seconds) of one N-process deployment."""
    cli = str(Path(sys.executable).parent / "safecdt-jax")  # the installed entry point
    base = [cli, "deploy", "--ckpt", str(args.ckpt),
            "--pair", args.pair, "--variant", "safe_cdt", "--seeds", str(seeds), "--episodes",
            str(args.episodes), "--set", f"horizon={args.horizon}"]
    address = f"127.0.0.1:{_free_port()}"
    commands = []
    for rank in range(n):
        cmd = [*base, "--out", str(folder / f"rank{rank}")]
        if n > 1:
            cmd = ["taskset", "-c", str(rank % os.cpu_count()), *cmd, "--coordinator",
                   address, "--num-processes", str(n), "--process-id", str(rank)]
        commands.append(cmd)
    start = time.perf_counter()
    logs = [open(folder / f"rank{rank}.log", "w") for rank in range(n)]
    procs = [subprocess.Popen(c, stdout=log, stderr=subprocess.STDOUT)
             for c, log in zip(commands, logs, strict=True)]
    codes = [p.wait(timeout=1800) for p in procs]
    wall = time.perf_counter() - start
    for log in logs:
        log.close()
    if any(codes):
        raise RuntimeError(f"N={n} S={seeds}: exit codes {codes}; logs in {folder}")
    results = json.loads((folder / "rank0" / "results.json").read_text())
    return float(results["timing"]["deploy_s"]), wall


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--ckpt", type=Path, required=True)
    p.add_argument("--pair", default="CG1-CG2")
    p.add_argument("--seeds", default="4,8,16")
    p.add_argument("--processes", default="1,2")
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--horizon", type=int, default=200)
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args()
    rows, points = [], []
    for n in (int(x) for x in args.processes.split(",")):
        for seeds in (int(x) for x in args.seeds.split(",")):
            deploy_s, wall_s = [], []
            for _ in range(args.repeats):
                with tempfile.TemporaryDirectory() as tmp:
                    d, w = _deploy(args, n, seeds, Path(tmp))
                deploy_s.append(d)
                wall_s.append(w)
            steps = seeds * args.episodes * args.horizon
            points.append({"processes": n, "seeds": seeds, "deploy_s": deploy_s,
                           "wall_s": wall_s, "env_steps": steps})
            last = deploy_s[-1]
            rows.append([n, seeds, " / ".join(f"{x:.1f}" for x in deploy_s),
                         f"{median(wall_s):.1f}", f"{steps / last:,.0f}"])
            print(rows[-1], flush=True)
    command = "python -m benchmarks.processes " + " ".join(sys.argv[1:])
    payload = {"machine": machine(), "command": command, "args": {
        k: str(v) for k, v in vars(args).items()}, "points": points}
    write_json(RESULTS / "processes.json", payload)
    body = (f"Safe-CDT on {args.pair}, {args.episodes} episodes of {args.horizon} steps per "
            f"seed; deploy s: process 0's sweep call per repeat (the first may compile); "
            f"steps/s from the last repeat.\n\n"
            + markdown_table(["processes", "seeds", "deploy s (repeats)", "command wall s",
                              "env steps/s"], rows))
    write_markdown(RESULTS / "processes.md", "Seeds x processes", command, body)


if __name__ == "__main__":
    main()
