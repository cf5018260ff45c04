"""Helpers shared by the benchmark scripts: timing, machine facts, atomic JSON, tables."""

import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import jax


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
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(payload, f, indent=2)
    os.replace(tmp, path)


def markdown_table(headers: list[str], rows: list[list]) -> str:
    """A GitHub markdown table."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)
