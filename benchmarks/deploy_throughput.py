"""Wall time and env steps/s of the full Safe-CDT deployment loop, many seeds in one call.

For each seed count S: one jitted sweep call deploying S seeds (LoRA steps, scheduler and all),
against a Python loop over S calls of the jitted single-seed `deploy` (same run, so the ratio is
fair on a noisy machine). Also the compile time of the sweep, cold (empty persistent cache, in a
fresh process) and warm (the persistent cache filled by that process).

    python -m benchmarks.deploy_throughput [--task CarGoal2] [--seeds 1,15,64] [--episodes 5]
        [--act sample|mean]

The model is the `cpu` preset with random weights: the cost of a deployment does not depend on
what the weights are. Episodes default to 5 (a whole stage) to keep the run short; env steps/s
and the seed-scaling ratio do not depend on the episode count. `--act`: the CDT acts with samples
of its policy (the deployment default since 2026-12-07) or its mean.
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time

import jax

from benchmarks.common import machine, markdown_table, median, write_json
from safecdt_jax import envs
from safecdt_jax.analysis.evaluate import ACTION_MODES, DEFAULT_ACTION_MODE
from safecdt_jax.deploy import (
    DeployConfig,
    deploy,
    init_adapters,
    make_spec,
    make_variant,
    seed_keys,
    stack_specs,
    sweep,
)
from safecdt_jax.model import CDTConfig, init_cdt, with_nominal_edges


def setup(task: str, preset: str, episodes: int, act: str = DEFAULT_ACTION_MODE):
    """(env, env params, model config, base params, deploy config, safe_cdt spec [1 run]);
    the model acts with samples of its policy (`act` "sample") or its mean ("mean")."""
    env, params = envs.make(task)
    model_cfg = with_nominal_edges(CDTConfig.preset(preset, env.observation_size,
                                                    env.action_size, env.episode_length))
    model_cfg = model_cfg.replace(stochastic_actions=ACTION_MODES[act])
    base = init_cdt(jax.random.PRNGKey(0), model_cfg)
    cfg = DeployConfig(episodes=episodes)
    spec = make_spec(make_variant("safe_cdt", cfg), 30.0, 20.0)
    return env, params, model_cfg, base, cfg, spec


def measure(task: str, preset: str, episodes: int, seeds: int, loop: bool, repeats: int,
            act: str = DEFAULT_ACTION_MODE) -> dict:
    """Median seconds of the S-seed sweep call, and of a Python loop over S single-seed calls."""
    env, params, model_cfg, base, cfg, spec = setup(task, preset, episodes, act)
    keys = seed_keys(0, seeds)
    specs = stack_specs([spec])
    static = dict(env=env, model_cfg=model_cfg, cfg=cfg)

    def swept():
        return jax.block_until_ready(sweep(keys, base, params, specs, **static))

    t = time.perf_counter()
    swept()
    first = time.perf_counter() - t
    runs = []
    for _ in range(repeats):
        t = time.perf_counter()
        swept()
        runs.append(time.perf_counter() - t)
    row = {"seeds": seeds, "sweep_first_s": first, "sweep_s": median(runs), "sweep_runs_s": runs}
    steps = seeds * episodes * env.episode_length
    row["env_steps_per_s"] = steps / row["sweep_s"]
    if loop:
        single = jax.jit(lambda k, lo: deploy(k, base, lo, params, spec, **static))
        loras = init_adapters(keys, base, model_cfg)
        one = lambda i: jax.tree.map(lambda x: x[i], loras)
        jax.block_until_ready(single(keys[0], one(0)))  # compile
        t = time.perf_counter()
        for i in range(seeds):
            jax.block_until_ready(single(keys[i], one(i)))
        row["loop_s"] = time.perf_counter() - t
        row["loop_over_sweep"] = row["loop_s"] / row["sweep_s"]
    return row


_COMPILE = """
import time, jax, sys
sys.path.insert(0, {root!r})
jax.config.update("jax_compilation_cache_dir", {cache!r})
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
from benchmarks.deploy_throughput import setup
from safecdt_jax.deploy import seed_keys, stack_specs, sweep
env, params, model_cfg, base, cfg, spec = setup({task!r}, {preset!r}, 1)
t = time.perf_counter()
jax.block_until_ready(sweep(seed_keys(0, 2), base, params, stack_specs([spec]), env=env,
                            model_cfg=model_cfg, cfg=cfg))
print("SECONDS", time.perf_counter() - t)
"""


def compile_seconds(task: str, preset: str) -> dict:
    """First-call seconds of a 1-episode, 2-seed sweep in fresh processes: cold, then warm cache.

    One episode runs too, so these include ~1 episode of work beyond compilation.
    """
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        code = _COMPILE.format(root=root, cache=cache, task=task, preset=preset)
        for label in ("cold", "warm"):
            proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                  cwd=root)
            line = [x for x in proc.stdout.splitlines() if x.startswith("SECONDS")]
            if proc.returncode or not line:
                raise RuntimeError(f"compile measurement failed: {proc.stderr[-1000:]}")
            out[f"{label}_s"] = float(line[0].split()[1])
    return out


def main() -> None:
    """Runs the measurements, prints the table, writes JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal2")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--seeds", default="1,15,64")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--loop-max", type=int, default=15,
                    help="Run the Python loop over single-seed calls up to this many seeds.")
    ap.add_argument("--no-compile", action="store_true", help="Skip the compile-time runs.")
    ap.add_argument("--act", default=DEFAULT_ACTION_MODE, choices=("sample", "mean"),
                    help="The CDT acts with samples of its policy (the default) or its mean.")
    ap.add_argument("--out", default="benchmarks/results/deploy_throughput.json")
    args = ap.parse_args()

    rows = []
    for s in (int(x) for x in args.seeds.split(",")):
        rows.append(measure(args.task, args.preset, args.episodes, s, s <= args.loop_max,
                            args.repeats, args.act))
        print(rows[-1], flush=True)
    base = next((r for r in rows if r["seeds"] == 1), None)
    for r in rows:
        r["vs_1_seed"] = r["sweep_s"] / base["sweep_s"] if base else float("nan")
    compile_s = {} if args.no_compile else compile_seconds(args.task, args.preset)
    table = markdown_table(
        ["seeds", "sweep s (median)", "env steps/s", "x time of 1 seed", "Python loop s",
         "loop / sweep"],
        [[r["seeds"], f"{r['sweep_s']:.2f}", f"{r['env_steps_per_s']:,.0f}",
          f"{r['vs_1_seed']:.2f}", f"{r['loop_s']:.2f}" if "loop_s" in r else "-",
          f"{r['loop_over_sweep']:.1f}x" if "loop_s" in r else "-"] for r in rows])
    print(f"\nSafe-CDT deployment, {args.task}, {args.preset} preset, {args.episodes} episodes "
          f"per seed, acting with its {args.act} ({jax.default_backend()})\n")
    print(table)
    if compile_s:
        print(f"\ncompile (1 episode, 2 seeds, fresh process): cold {compile_s['cold_s']:.1f} s, "
              f"warm persistent cache {compile_s['warm_s']:.1f} s")
    write_json(args.out, {"machine": machine(), "task": args.task, "preset": args.preset,
                          "episodes": args.episodes, "act": args.act, "rows": rows,
                          "compile": compile_s,
                          "table": table})


if __name__ == "__main__":
    main()
