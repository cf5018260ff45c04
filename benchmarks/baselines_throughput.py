"""Offline-baseline training throughput: our BCQL, BEARL and CPQ against OSRL's PyTorch ones,
and all seeds vmapped against sequential runs.

(1) Per update, CarGoal sizes (obs 72, act 2, L 1000), batch 512, OSRL's networks: one jitted
chunk of `--steps` updates (batches sampled inside the scan) against `--steps` calls of OSRL's
`train_one_step` on a fixed batch (its DataLoader not counted), alternated A B A B on the same
`--threads` cores; medians and per-pair ratios. (2) Ours only: one vmapped call training
`--seeds` seeds against `--seeds` sequential single-seed calls, the same total updates.
Writes benchmarks/results/baselines_throughput.{json,md}.

    python -m benchmarks.baselines_throughput [--threads 1] [--steps 10] [--repeats 3]
"""

import argparse
import time
from pathlib import Path

from benchmarks.common import machine, markdown_table, pin_threads, stats, write_json

OBS, ACT, HORIZON = 72, 2, 1000
OUT = Path(__file__).resolve().parent / "results"


def _our_runner(algo: str, steps: int, seeds: int | None):
    """A callable timing one chunk of `steps` updates (vmapped over `seeds` when given)."""
    import jax
    import numpy as np

    from safecdt_jax.baselines import common, preset
    from safecdt_jax.baselines.train import make_algorithm, make_chunk
    from safecdt_jax.data.dataset import make_dataset

    rng = np.random.default_rng(0)
    n = 16
    data, _ = common.transitions(make_dataset(
        rng.normal(size=(n, HORIZON, OBS)), rng.uniform(-1, 1, (n, HORIZON, ACT)),
        rng.uniform(0, 0.05, (n, HORIZON)), (rng.uniform(size=(n, HORIZON)) < 0.05) * 1.0,
        np.full(n, HORIZON)))
    cfg = preset(algo, "osrl", chunk=steps)
    fns = make_algorithm(cfg, OBS, ACT, HORIZON)
    chunk = make_chunk(cfg, fns)
    if seeds is None:
        state = fns.init(jax.random.PRNGKey(0))
        call = jax.jit(chunk)
        key = jax.random.PRNGKey(1)
    else:
        state = jax.vmap(fns.init)(jax.random.split(jax.random.PRNGKey(0), seeds))
        call = jax.jit(jax.vmap(chunk, in_axes=(0, 0, None)))
        key = jax.random.split(jax.random.PRNGKey(1), seeds)
    jax.block_until_ready(call(state, key, data))  # compile

    def run() -> dict:
        t = time.perf_counter()
        jax.block_until_ready(call(state, key, data))
        return {"seconds": time.perf_counter() - t, "steps": steps}

    return run


def main() -> None:
    """Measures, prints the tables, writes JSON and markdown."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--steps", type=int, default=10, help="updates per timed call")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--algos", default="bcql,bearl,cpq")
    p.add_argument("--no-peer", action="store_true", help="skip OSRL (ours only)")
    args = p.parse_args()
    pin_threads(args.threads)  # before JAX creates its CPU client; the worker inherits it
    from benchmarks.run_all import CPU_PER_WALL, Peer, alternate, pair_ratios

    algos = args.algos.split(",")
    osrl = None
    if not args.no_peer:
        from benchmarks.peers import setup

        setup.ensure("osrl")
        osrl = Peer("osrl", setup.ROOT / "workers.log")  # what the peer prints (git-ignored)
    per_update, seeds_rows = [], []
    for algo in algos:
        ours = _our_runner(algo, args.steps, None)
        if osrl is not None:
            res = alternate(lambda a=algo: osrl("baseline_train", algo=a, batch=512,
                                                steps=args.steps, obs_dim=OBS, act_dim=ACT,
                                                episode_len=HORIZON),
                            {"ours": ours}, args.repeats)
            peer_ms = [1e3 * a["seconds"] / a["steps"] for a in res["peer"]]
        else:
            res = {"ours": [ours() for _ in range(args.repeats)]}
            peer_ms = []
        our_ms = [1e3 * a["seconds"] / a["steps"] for a in res["ours"]]
        row = {"algo": algo, "ours_ms": stats(our_ms),
               "peer_ms": stats(peer_ms) if peer_ms else None,
               "speedup": pair_ratios(peer_ms, our_ms) if peer_ms else None}
        per_update.append(row)
        print(f"{algo}: {row}", flush=True)
        batched = _our_runner(algo, args.steps, args.seeds)
        times_v, times_s = [], []
        for _ in range(args.repeats):
            times_v.append(batched()["seconds"])
            times_s.append(args.seeds * ours()["seconds"])  # the same program, run per seed
        seeds_rows.append({"algo": algo, "seeds": args.seeds, "vmapped_s": stats(times_v),
                           "sequential_s": stats(times_s),
                           "speedup": pair_ratios(times_s, times_v)})
        print(f"{algo} x{args.seeds}: {seeds_rows[-1]}", flush=True)
    if osrl is not None:
        osrl.close()
    payload = {"machine": machine(), "threads": args.threads, "steps_per_call": args.steps,
               "batch": 512, "sizes": {"obs": OBS, "act": ACT, "episode_len": HORIZON},
               "per_update": per_update, "seeds": seeds_rows,
               "cpu_per_wall": {k: stats(v) for k, v in CPU_PER_WALL.items() if v}}
    write_json(OUT / "baselines_throughput.json", payload)
    rows = [[r["algo"], f"{r['ours_ms']['median']:.0f}",
             "-" if r["peer_ms"] is None else f"{r['peer_ms']['median']:.0f}",
             "-" if r["speedup"] is None else f"{r['speedup']['median']:.2f}x"]
            for r in per_update]
    table1 = markdown_table(["algorithm", "ours ms/update", "OSRL ms/update",
                             "speedup (median of pairs)"], rows)
    rows = [[r["algo"], r["seeds"], f"{r['vmapped_s']['median']:.2f}",
             f"{r['sequential_s']['median']:.2f}", f"{r['speedup']['median']:.2f}x"]
            for r in seeds_rows]
    table2 = markdown_table(["algorithm", "seeds", f"vmapped s / {args.steps} updates",
                             "sequential s", "speedup"], rows)
    text = (f"# Offline baselines: training throughput\n\n`python -m "
            f"benchmarks.baselines_throughput --threads {args.threads} --steps {args.steps} "
            f"--repeats {args.repeats}`, {payload['machine']['date']}, "
            f"{payload['machine']['cpus']}-core CPU, batch 512, CarGoal sizes, OSRL's "
            f"networks.\n\n{table1}\n\n{table2}\n")
    from safecdt_jax.io import write_text_atomic

    write_text_atomic(OUT / "baselines_throughput.md", text)
    print(text)


if __name__ == "__main__":
    main()
