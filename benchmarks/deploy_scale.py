"""How one deployment call scales with seeds and episodes (wall time per episode, env steps/s,
peak memory), and what leaving the LoRA steps out of a zero-shot sweep saves.

    python -m benchmarks.deploy_scale [--task CarGoal2] [--seeds 1,15,64,256]
        [--episodes 50,100] [--run 2] [--zero-shot-seeds 15] [--devices 1,2]
        [--only scale,zero_shot,devices]

Scale: each (seeds, episodes) point runs in a fresh process: it compiles the Safe-CDT sweep
for a deployment of `episodes` episodes (so the online buffer holds all of them), initialises
the carry, runs `--run` episodes (compiling), then times the next `--run` episodes with the
same program (every episode costs the same: the rollout, 10 LoRA steps of 32 windows, the
scheduler), and reports the process's peak resident memory (ru_maxrss). The whole deployment
costs the per-episode time x episodes.

Zero-shot: a `zero_shot` sweep of `--zero-shot-seeds` seeds with the program that computes and
discards the LoRA steps (before) and the one without them (after, `deploy/sweep.py`), the same
bits, alternated, median of `--repeats`.

Devices: the full Safe-CDT `sweep` of `--device-seeds` seeds x `--device-episodes` episodes in a
fresh process per device count N, with `XLA_FLAGS=--xla_force_host_platform_device_count=N`
(N CPU devices; `sweep` shards the seed axis over them); the first call compiles, then the
median of `--repeats` calls, and the summed cost over seeds and episodes (the same on every N).

The model is the `cpu` preset with random weights (cost does not depend on the weights).
"""

import argparse
import json
import os
import sys
import time

import jax
import numpy as np

from benchmarks.common import (
    machine,
    markdown_table,
    median,
    run_script,
    write_json,
    write_markdown,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

_POINT = """
import json, resource, sys, time
sys.path.insert(0, {root!r})
import jax, numpy as np
from benchmarks.deploy_throughput import setup
from safecdt_jax.deploy import DeployConfig, init_adapters, seed_keys, stack_specs
from safecdt_jax.deploy.sweep import _compiled
env, params, model_cfg, base, _, spec = setup({task!r}, "cpu", {episodes})
cfg = DeployConfig(episodes={episodes})
keys = seed_keys(0, {seeds})
specs = stack_specs([spec])
init_all, run_all = _compiled(env, model_cfg, cfg, False, True)
t = time.perf_counter()
carry = jax.block_until_ready(init_all(keys, init_adapters(keys, base, model_cfg), specs))
# The scan length is a shape: time a second call of the same length, not a recompile.
carry, _ = jax.block_until_ready(run_all(carry, np.arange({run}, dtype=np.int32), base, params,
                                         specs))
first = time.perf_counter() - t
t = time.perf_counter()
index = np.arange({run}, 2 * {run}, dtype=np.int32)
carry, m = jax.block_until_ready(run_all(carry, index, base, params, specs))
wall = time.perf_counter() - t
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
print("RESULT", json.dumps({{"first_s": first, "episode_s": wall / {run}, "peak_rss_gb": rss}}))
"""


_DEVICES = """
import json, sys, time
sys.path.insert(0, {root!r})
import jax, numpy as np
from benchmarks.deploy_throughput import setup
from safecdt_jax.deploy import seed_keys, stack_specs, sweep
env, params, model_cfg, base, cfg, spec = setup({task!r}, "cpu", {episodes})
keys, specs = seed_keys(0, {seeds}), stack_specs([spec])
def call():
    return jax.block_until_ready(sweep(keys, base, params, specs, env=env, model_cfg=model_cfg,
                                       cfg=cfg))
t = time.perf_counter()
m = call()
first = time.perf_counter() - t
runs = []
for _ in range({repeats}):
    t = time.perf_counter()
    m = call()
    runs.append(time.perf_counter() - t)
print("RESULT", json.dumps({{"devices": len(jax.devices()), "first_s": first, "runs_s": runs,
                            "cost_sum": float(np.asarray(m.costs).sum())}}))
"""


def devices_point(task: str, n_devices: int, seeds: int, episodes: int, repeats: int) -> dict:
    """The full sweep on `n_devices` forced CPU devices in a fresh process (module docstring)."""
    code = _DEVICES.format(root=ROOT, task=task, seeds=seeds, episodes=episodes, repeats=repeats)
    flags = os.environ.get("XLA_FLAGS", "")
    env = {**os.environ,
           "XLA_FLAGS": f"{flags} --xla_force_host_platform_device_count={n_devices}".strip()}
    try:
        out = {"seeds": seeds, "episodes": episodes, **run_script(code, env=env, tail=300)}
    except RuntimeError as e:
        return {"devices": n_devices, "error": str(e)}
    out["median_s"] = median(out["runs_s"])
    return out


def scale_point(task: str, seeds: int, episodes: int, run: int) -> dict:
    """One (seeds, episodes) point in a fresh process (see the module docstring)."""
    code = _POINT.format(root=ROOT, task=task, seeds=seeds, episodes=episodes, run=run)
    try:
        out = {"seeds": seeds, "episodes": episodes, **run_script(code, tail=300)}
    except RuntimeError as e:
        return {"seeds": seeds, "episodes": episodes, "error": str(e)}
    steps_per_episode = seeds * 1000  # CarGoal2's horizon; the cost is per scanned step
    out["env_steps_per_s"] = steps_per_episode / out["episode_s"]
    out["deployment_min"] = out["episode_s"] * episodes / 60
    # the online buffer: observations, actions, rewards, costs for every episode and step
    out["buffer_gb"] = seeds * episodes * 1000 * (72 + 2 + 2) * 4 / 2**30
    return out


def zero_shot(task: str, seeds: int, episodes: int, repeats: int) -> dict:
    """Median seconds of a zero-shot sweep with and without the LoRA steps (same bits)."""
    from benchmarks.deploy_throughput import setup
    from safecdt_jax.deploy import (
        DeployConfig,
        init_adapters,
        make_spec,
        make_variant,
        seed_keys,
        stack_specs,
    )
    from safecdt_jax.deploy.sweep import _compiled

    env, params, model_cfg, base, _, _ = setup(task, "cpu", episodes)
    cfg = DeployConfig(episodes=episodes)
    keys = seed_keys(0, seeds)
    specs = stack_specs([make_spec(make_variant("zero_shot", cfg), 30.0, 20.0)])
    lora = init_adapters(keys, base, model_cfg)
    index = np.arange(episodes, dtype=np.int32)
    progs = {name: _compiled(env, model_cfg, cfg, False, finetune)
             for name, finetune in (("with_lora_steps", True), ("without", False))}
    out, metrics = {}, {}
    for name, (init_all, run_all) in progs.items():  # compile
        metrics[name] = jax.device_get(run_all(init_all(keys, lora, specs), index, base, params,
                                               specs)[1])
    same = all(np.array_equal(getattr(metrics["without"], f), getattr(metrics["with_lora_steps"],
                                                                      f))
               for f in ("returns", "costs", "ctg_target"))
    times = {name: [] for name in progs}
    for _ in range(repeats):
        for name, (init_all, run_all) in progs.items():
            carry = jax.block_until_ready(init_all(keys, lora, specs))
            t = time.perf_counter()
            jax.block_until_ready(run_all(carry, index, base, params, specs))
            times[name].append(time.perf_counter() - t)
    for name, ts in times.items():
        out[f"{name}_s"] = median(ts)
        out[f"{name}_runs_s"] = ts
    out["speedup"] = out["with_lora_steps_s"] / out["without_s"]
    out["same_returns_and_costs"] = same
    return {"seeds": seeds, "episodes": episodes, **out}


def main() -> None:
    """Runs both measurements, prints the tables, writes JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal2")
    ap.add_argument("--seeds", default="1,15,64,256")
    ap.add_argument("--episodes", default="50,100")
    ap.add_argument("--run", type=int, default=2, help="Episodes timed per scale point.")
    ap.add_argument("--zero-shot-seeds", type=int, default=15)
    ap.add_argument("--zero-shot-episodes", type=int, default=5)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--devices", default="1,2", help="Forced CPU device counts to compare.")
    ap.add_argument("--device-seeds", type=int, default=16)
    ap.add_argument("--device-episodes", type=int, default=2)
    ap.add_argument("--only", default="scale,zero_shot,devices",
                    help="Which measurements to run (the others keep their saved results).")
    ap.add_argument("--out", default="benchmarks/results/deploy_scale.json")
    args = ap.parse_args()
    only = set(args.only.split(","))
    unknown = only - {"scale", "zero_shot", "devices"}
    if unknown:
        raise SystemExit(f"--only: unknown measurement(s) {sorted(unknown)}")
    saved = json.load(open(args.out)) if os.path.exists(args.out) else {}

    start = time.perf_counter()
    zs = saved.get("zero_shot")
    if "zero_shot" in only:
        zs = zero_shot(args.task, args.zero_shot_seeds, args.zero_shot_episodes, args.repeats)
        print(zs, flush=True)
    rows = saved.get("rows", [])
    if "scale" in only:
        rows = []
        for e in (int(x) for x in args.episodes.split(",")):
            for s in (int(x) for x in args.seeds.split(",")):
                rows.append(scale_point(args.task, s, e, args.run))
                print(rows[-1], flush=True)
    dev = saved.get("devices", [])
    if "devices" in only:
        dev = []
        for n in (int(x) for x in args.devices.split(",")):
            dev.append(devices_point(args.task, n, args.device_seeds, args.device_episodes,
                                     args.repeats))
            print(dev[-1], flush=True)
    dev_ok = [d for d in dev if "error" not in d]
    one = next((d["median_s"] for d in dev_ok if d["devices"] == 1), None)
    dev_table = markdown_table(
        ["CPU devices", "seeds x episodes", "median s", "speedup vs 1", "first call s",
         "summed cost"],
        [[d["devices"], f"{d['seeds']} x {d['episodes']}", f"{d['median_s']:.2f}",
          f"{one / d['median_s']:.2f}x" if one else "", f"{d['first_s']:.0f}",
          f"{d['cost_sum']:.0f}"] for d in dev_ok]
        + [[d["devices"], d["error"], "", "", "", ""] for d in dev if "error" in d])
    ok = [r for r in rows if "error" not in r]
    table = markdown_table(
        ["seeds", "episodes", "s per episode", "env steps/s", "deployment (min)",
         "buffer (GB)", "peak RSS (GB)", "compile + first episodes s"],
        [[r["seeds"], r["episodes"], f"{r['episode_s']:.2f}", f"{r['env_steps_per_s']:,.0f}",
          f"{r['deployment_min']:.1f}", f"{r['buffer_gb']:.2f}", f"{r['peak_rss_gb']:.2f}",
          f"{r['first_s']:.0f}"] for r in ok]
        + [[r["seeds"], r["episodes"], r["error"], "", "", "", "", ""] for r in rows
           if "error" in r])
    zs_table = markdown_table(
        ["seeds x episodes", "with LoRA steps s", "without s", "speedup", "same bits"],
        [[f"{zs['seeds']} x {zs['episodes']}", f"{zs['with_lora_steps_s']:.2f}",
          f"{zs['without_s']:.2f}", f"{zs['speedup']:.2f}x", zs["same_returns_and_costs"]]]
    ) if zs else ""
    print(f"\nSafe-CDT deployment on {args.task}, cpu preset ({jax.default_backend()}), "
          f"{time.perf_counter() - start:.0f} s\n\n{table}\n\nzero-shot sweep\n\n{zs_table}"
          f"\n\nforced CPU devices\n\n{dev_table}")
    # When each part was last measured (the others keep the saved results and dates).
    measured = saved.get("measured") or {  # results saved before dates were kept per part
        part: saved["machine"]["date"] for part in ("scale", "zero_shot") if "machine" in saved}
    measured.update({part: machine()["date"] for part in only})
    write_json(args.out, {"machine": machine(), "measured": measured, "task": args.task,
                          "rows": rows,
                          "zero_shot": zs, "devices": dev, "table": table,
                          "zero_shot_table": zs_table, "devices_table": dev_table,
                          "command": "python -m benchmarks.deploy_scale " + " ".join(sys.argv[1:])})
    when = ", ".join(f"{k} {v}" for k, v in sorted(measured.items()))
    write_markdown(os.path.splitext(args.out)[0] + ".md", "The deployment at scale",
                   "python -m benchmarks.deploy_scale " + " ".join(sys.argv[1:]),
                   f"{args.task}, `cpu` preset, full Safe-CDT loop unless said (measured: {when})."
                   f"\n\nOne call per point:\n\n{table}\n\nZero-shot sweep with and without "
                   f"the LoRA steps:\n\n{zs_table}\n\nForced CPU devices:\n\n{dev_table}")


if __name__ == "__main__":
    main()
