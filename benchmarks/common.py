"""Helpers shared by the benchmark scripts: timing, machine facts, atomic JSON, tables."""

import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax

from safecdt_jax.io import atomic_path
from safecdt_jax.results.tables import markdown_table  # noqa: F401  (one home; re-exported)


def machine() -> dict:
    """What the numbers were measured on: host, CPU count, JAX backend and versions."""
    import mujoco

    return {"host": platform.node(), "cpus": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "mujoco": mujoco.__version__,
            "backend": jax.default_backend(), "device": str(jax.devices()[0]),
            "date": time.strftime("%Y-%m-%d %H:%M:%S")}


def time_call(fn, *args, repeats: int = 3) -> tuple[float, list[float]]:
    """(first-call seconds including compilation, [seconds of each of `repeats` later calls])."""
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t)
    return first, runs


def median(xs: list[float]) -> float:
    """Median of a list of timings (robust on a noisy machine)."""
    return statistics.median(xs)


def write_json(path: str | Path, payload: dict) -> None:
    """Writes `payload` to `path` atomically (temp file in the same folder, then rename)."""
    with atomic_path(path, suffix=".json") as tmp, open(tmp, "w") as f:
        json.dump(payload, f, indent=2)


def write_markdown(path: str | Path, title: str, command: str, body: str) -> None:
    """Writes a benchmark's result page atomically: `# title`, the command with the date and
    machine that made it, then `body` (tables). `benchmarks.run_all` folds these pages into
    BENCHMARKS.md."""
    m = machine()
    text = (f"# {title}\n\n`{command}`, {m['date']}, {m['cpus']}-core CPU ({m['host']}), "
            f"jax {m['jax']} on {m['backend']}.\n\n{body.strip()}\n")
    with atomic_path(path, suffix=".md") as tmp:
        Path(tmp).write_text(text)


def run_script(code: str, env: dict | None = None, tail: int = 2000) -> dict:
    """Runs `python -c code` in a fresh process at the repository root and returns the JSON the
    script printed after `RESULT ` (a fresh process: its own JAX backend, flags and peak RSS).
    RuntimeError `exit N: <last `tail` characters of stderr>` if it failed or printed none."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=root,
                          env=env)
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT")]
    if proc.returncode or not line:
        raise RuntimeError(f"exit {proc.returncode}: {proc.stderr.strip()[-tail:]}")
    return json.loads(line[0].split(" ", 1)[1])


def stats(xs: list[float]) -> dict:
    """Median, min, max and count of repeated measurements (what the peer tables print)."""
    return {"median": median(xs), "min": min(xs), "max": max(xs), "n": len(xs)}


def pin_threads(n: int) -> list[int]:
    """Limits this process and the processes it starts later to `n` CPU cores and threads.

    XLA's flags alone do not hold XLA to one thread (its CPU runtime still runs some work on a
    second thread), so every thread of this process is also pinned to `n` cores; child
    processes inherit that. Must run before JAX runs anything: XLA reads its flags when the CPU
    client is created. Returns the cores used.
    """
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise RuntimeError("pin_threads must be called before JAX creates its backends")
    eigen = "true" if n > 1 else "false"
    flags = f"--xla_cpu_multi_thread_eigen={eigen} intra_op_parallelism_threads={n}"
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {flags}".strip()
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "BENCH_THREADS"):
        os.environ[var] = str(n)
    cores = sorted(os.sched_getaffinity(0))[-n:]
    for tid in os.listdir("/proc/self/task"):  # threads that exist already (e.g. BLAS pools)
        os.sched_setaffinity(int(tid), cores)
    return cores
