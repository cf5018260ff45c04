"""Cold and warm compile of the deployment program: what the persistent XLA cache saves.

    python -m benchmarks.compile_time [--task CarGoal2] [--seeds 15] [--episodes 50]
        [--preset cpu]

Two fresh processes share one empty temporary cache folder (`jax_compilation_cache_dir`):
the first compiles the Safe-CDT sweep's programs (init and episodes, `deploy/sweep.py`) from
nothing and writes them to the cache, the second loads them. This is done twice in one run:
without and with the traced episodes program stored on disk (`safecdt_jax.programs`, what
every `safecdt-jax` command does). Each process reports, for the episodes program, the seconds
JAX spends tracing and lowering it (or loading the stored trace), XLA's compile (or the cache
load), and the wall time of the process up to the first episode's result (imports, env model
build, compile, one episode). Writes benchmarks/results/compile_time.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile

from benchmarks.common import machine, markdown_table, run_script, write_json, write_markdown

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_PROC = """
import json, sys, time
t0 = time.perf_counter()
sys.path.insert(0, {root!r})
import jax, numpy as np
jax.config.update("jax_compilation_cache_dir", {cache!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
from benchmarks.deploy_throughput import setup
from safecdt_jax import programs
from safecdt_jax.deploy import init_adapters, seed_keys, stack_specs
from safecdt_jax.deploy.sweep import _compiled, stored_episodes
programs.enable({programs!r})
env, params, model_cfg, base, cfg, spec = setup({task!r}, {preset!r}, {episodes})
keys, specs = seed_keys(0, {seeds}), stack_specs([spec])
lora = init_adapters(keys, base, model_cfg)
init_all, run_all = _compiled(env, model_cfg, cfg, False, True)
t = time.perf_counter()
init_exe = init_all.lower(keys, lora, specs).compile()
init_s = time.perf_counter() - t
carry = init_exe(keys, lora, specs)
index = np.arange(1, dtype=np.int32)
args = (carry, index, base, params, specs)
t = time.perf_counter()
# What `deploy.sweep` does: with storing on, export (cold) or load (warm) the traced program.
run = stored_episodes(run_all, args, env=env, model_cfg=model_cfg, cfg=cfg,
                      env_params_batched=False, finetune=True)
lowered = run.trace(*args).lower()
trace_s = time.perf_counter() - t
t = time.perf_counter()
run_exe = lowered.compile()
run_s = time.perf_counter() - t
jax.block_until_ready(run_exe(*args))
print("RESULT", json.dumps({{"init_compile_s": init_s, "episodes_trace_s": trace_s,
                            "episodes_compile_s": run_s,
                            "to_first_episode_s": time.perf_counter() - t0}}))
"""


def one_process(cache: str, stored: bool, args) -> dict:
    """One fresh process compiling (or loading) the programs; its timings. With `stored`
    the traced program is kept in (or loaded from) `cache/programs` (`safecdt_jax.programs`)."""
    code = _PROC.format(root=ROOT, cache=cache, task=args.task, preset=args.preset,
                        episodes=args.episodes, seeds=args.seeds,
                        programs=os.path.join(cache, "programs") if stored else None)
    return run_script(code)


def main() -> None:
    """Cold, then warm; prints the table and writes the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal2")
    ap.add_argument("--seeds", type=int, default=15)
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--out", default="benchmarks/results/compile_time.json")
    args = ap.parse_args()
    runs = {}
    for stored in (False, True):  # both in one run, so the saving is measured on one day
        with tempfile.TemporaryDirectory() as cache:
            for start in ("cold", "warm"):
                runs[f"{start}, traced program {'stored' if stored else 'not stored'}"] = \
                    one_process(cache, stored, args)
    rows = [[name, f"{r['init_compile_s']:.1f}", f"{r['episodes_trace_s']:.1f}",
             f"{r['episodes_compile_s']:.1f}", f"{r['to_first_episode_s']:.1f}"]
            for name, r in runs.items()]
    table = markdown_table(["caches", "init lower + compile s",
                            "episodes: trace and lower (or load) s",
                            "episodes: XLA compile (or cache load) s",
                            "process start to first episode s"], rows)
    print(f"{args.task}, {args.preset} preset, {args.seeds} seeds x {args.episodes} episodes\n\n"
          f"{table}")
    command = "python -m benchmarks.compile_time " + " ".join(sys.argv[1:])
    write_json(args.out, {"machine": machine(), "task": args.task, "preset": args.preset,
                          "seeds": args.seeds, "episodes": args.episodes, "runs": runs,
                          "table": table, "command": command})
    write_markdown(os.path.splitext(args.out)[0] + ".md", "Compile time", command,
                   f"The Safe-CDT sweep's programs, {args.task}, `{args.preset}` preset, "
                   f"{args.seeds} seeds x {args.episodes} episodes; two fresh processes on one "
                   f"empty cache folder, without and then with the traced program stored."
                   f"\n\n{table}")


if __name__ == "__main__":
    main()
