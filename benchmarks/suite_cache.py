"""What the test suite's persistent compilation cache saves: the suite cold, then warm.

    python -m benchmarks.suite_cache [--runs cold,warm] [--pytest-args "..."]

Runs the README's test command (`python -m pytest -q`: one process per core, pytest-xdist) in
fresh processes on one empty temporary cache folder (`JAX_COMPILATION_CACHE_DIR`, which
tests/conftest.py reads before it falls back to `~/.cache/safecdt-jax-tests/xla`): the first
run compiles every program and writes it to the cache, the next loads them. Each run reports
its wall time, pytest's summary line and the cache's size afterwards. The saving is cold minus
warm; what is left warm is tracing, the tests' own computation and the processes' start.
Writes benchmarks/results/suite_cache.{json,md}.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import machine, markdown_table, write_json, write_markdown

ROOT = Path(__file__).resolve().parents[1]


def folder_size_mb(path: str) -> float:
    """Total size of the files under `path`, in MB (10^6 bytes)."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file()) / 1e6


def one_run(cache: str, pytest_args: list[str]) -> dict:
    """One run of the suite on `cache`: wall seconds, exit code, pytest's last line, cache MB."""
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache}
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", *pytest_args], cwd=ROOT,
                          env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    # With the project's `-q` twice pytest may print only dots: count them then.
    lines = [x for x in proc.stdout.splitlines() if x.strip()]
    told = [x for x in lines if " passed" in x or " failed" in x or " error" in x]
    dots = sum(x.count(".") for x in lines if set(x.split("[")[0].strip()) <= set(".sFEx"))
    summary = told[-1] if told else f"{dots} passed (dots)" if dots else proc.stderr[-500:]
    return {"wall_s": wall, "returncode": proc.returncode, "summary": summary,
            "cache_mb": folder_size_mb(cache)}


def main() -> None:
    """Cold, then warm, on one empty cache; prints the table and writes the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="cold,warm", help="names of the runs, in order")
    ap.add_argument("--pytest-args", default="", help="extra pytest arguments, one string")
    ap.add_argument("--out", default="benchmarks/results/suite_cache.json")
    args = ap.parse_args()
    extra = args.pytest_args.split()
    runs = {}
    with tempfile.TemporaryDirectory() as cache:
        for name in args.runs.split(","):
            runs[name] = one_run(cache, extra)
            print(name, runs[name], flush=True)
    names = list(runs)
    first = runs[names[0]]["wall_s"]
    rows = [[n, f"{r['wall_s'] / 60:.1f}", f"{first / r['wall_s']:.2f}x", f"{r['cache_mb']:.0f}",
             r["summary"]] for n, r in runs.items()]
    table = markdown_table(["run", "wall (min)", f"speedup vs {names[0]}", "cache (MB)",
                            "pytest"], rows)
    print(table)
    command = "python -m benchmarks.suite_cache " + " ".join(sys.argv[1:])
    write_json(args.out, {"machine": machine(), "runs": runs, "pytest_args": extra,
                          "command": command})
    write_markdown(os.path.splitext(args.out)[0] + ".md", "The test suite's compilation cache",
                   command, f"The README's test command on one empty cache folder, run after "
                   f"run.\n\n{table}")


if __name__ == "__main__":
    main()
