"""Env steps per second of every task at several batch sizes, whole episodes with resets.

Each measurement is one jitted call of `jax.vmap` over `batch` random-policy episodes of the
task's full length (reset included, as the reference's "with resets" figures). Compile time is
reported separately; throughput is the median of `--repeats` calls.

    python -m benchmarks.env_throughput [--tasks CarGoal1,...] [--batches 1,15,256,1024]
"""

import argparse

import jax

from benchmarks.common import machine, markdown_table, median, time_call, write_json
from safecdt_jax import envs
from safecdt_jax.envs.rollout import run_episode

# Native Safety-Gymnasium 1.0.0, one env on one core of this machine class, resets amortised.
REFERENCE_WITH_RESETS = {"CarGoal1": 575, "PointCircle1": 425}
REFERENCE_NO_RESETS = {"CarGoal1": 1537, "PointCircle1": 5711}


def measure(name: str, batch: int, repeats: int) -> dict:
    """Compile seconds and median env steps/s for `batch` parallel episodes of task `name`."""
    env, params = envs.make(name)
    fn = jax.jit(jax.vmap(lambda k: run_episode(env, params, k)))
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    first, runs = time_call(fn, keys, repeats=repeats)
    steps = batch * env.episode_length
    return {"task": name, "batch": batch, "compile_s": first - median(runs),
            "steps_per_s": steps / median(runs), "runs_s": runs}


def main() -> None:
    """Runs the sweep, prints the table, writes JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", default=",".join(envs.NAMES))
    ap.add_argument("--batches", default="1,15,256,1024")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default="benchmarks/results/env_throughput.json")
    args = ap.parse_args()
    results = []
    for name in args.tasks.split(","):
        for batch in (int(b) for b in args.batches.split(",")):
            r = measure(name, batch, args.repeats)
            results.append(r)
            print(f"{name:13s} batch {batch:5d}: {r['steps_per_s']:10.0f} steps/s "
                  f"(compile {r['compile_s']:.1f} s)", flush=True)
    batches = sorted({r["batch"] for r in results})
    rows = []
    for name in dict.fromkeys(r["task"] for r in results):
        by_batch = {r["batch"]: r for r in results if r["task"] == name}
        ref = REFERENCE_WITH_RESETS.get(name)
        best = by_batch.get(256)
        ratio = f"{best['steps_per_s'] / ref:.0f}x" if ref and best else "-"
        rows.append([name] + [f"{by_batch[b]['steps_per_s']:,.0f}" if b in by_batch else "-"
                              for b in batches]
                    + [f"{max(r['compile_s'] for r in by_batch.values()):.1f}", ratio])
    table = markdown_table(["task"] + [f"batch {b}" for b in batches]
                           + ["compile s (max)", "vs native @256"], rows)
    print("\nEnv steps/s, full episodes with resets (median of repeats)\n")
    print(table)
    write_json(args.out, {"machine": machine(), "results": results, "table": table,
                          "reference_with_resets": REFERENCE_WITH_RESETS,
                          "reference_no_resets": REFERENCE_NO_RESETS})


if __name__ == "__main__":
    main()
