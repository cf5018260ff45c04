"""CDT training throughput (updates/s, sequences/s) and inference latency, per preset and batch.

Training: one jitted `train_chunk` call (`lax.scan` over updates, each sampling its K-step windows
on the device from synthetic episodes of the task's sizes, then OSRL's AdamW + temperature step,
dropout on), timed after compilation; median of `--repeats` calls. Inference: `last_action` on a
full K-step window (the deployment's per-step call) at batch 1 and 15.
Reference: OSRL's own `CDTTrainer.train_one_step` (PyTorch 2, one CPU thread, this machine class,
measured by `benchmarks.run_all`, BENCHMARKS.md): 184 ms at batch 64, 736 ms at 256, ~11.5 s
at 2048; 1.8 ms per forward at batch 1.

    python -m benchmarks.train_throughput [--runs "osrl:64,256,2048;cpu:32,64"] [--tasks CarGoal]
"""

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import machine, markdown_table, median, time_call, write_json
from safecdt_jax.model import (
    CDTConfig,
    OptimConfig,
    count_params,
    init_train_state,
    last_action,
    with_nominal_edges,
)
from safecdt_jax.pretrain import PretrainConfig, TrainData, make_train_chunk, run_key

# (obs_dim, act_dim, episode_len) of the task families; the robot's level does not change them.
SIZES = {"CarGoal": (72, 2, 1000), "CarCircle": (40, 2, 500), "PointGoal": (60, 2, 1000),
         "PointCircle": (28, 2, 500)}
OSRL_TORCH_MS = {64: 184.0, 256: 736.0, 2048: 11_500.0}  # per update, 1 thread (ref. 6.2)
OSRL_TORCH_INFER_MS = {1: 1.8}


def synthetic_data(obs_dim: int, act_dim: int, horizon: int, n: int = 64) -> TrainData:
    """`n` full-length random episodes on the device (costs 0/1 at rate 3%, small rewards)."""
    rng = np.random.default_rng(0)
    return jax.device_put(TrainData(
        observations=rng.normal(size=(n, horizon, obs_dim)).astype(np.float32),
        actions=rng.uniform(-1, 1, (n, horizon, act_dim)).astype(np.float32),
        rewards=rng.uniform(0, 0.05, (n, horizon)).astype(np.float32),
        costs=(rng.uniform(size=(n, horizon)) < 0.03).astype(np.float32),
        lengths=np.full(n, horizon, np.int32),
        return_offset=np.zeros(n, np.float32),
        cost_offset=np.zeros(n, np.float32),
    ))


def measure_train(preset: str, task: str, batch: int, repeats: int, work: int) -> dict:
    """Compile seconds and median updates/s of `train_chunk` for one (preset, task, batch).

    Each timed call runs `chunk = clip(work // batch, 1, 64)` updates (about `work` sequences).
    """
    obs, act, horizon = SIZES[task]
    cfg = with_nominal_edges(CDTConfig.preset(preset, obs, act, horizon))
    data = synthetic_data(obs, act, horizon)
    weights = jnp.full(data.lengths.shape, 1.0 / data.lengths.shape[0])
    chunk = int(np.clip(work // batch, 1, 64))
    fn = make_train_chunk(cfg, OptimConfig(), PretrainConfig(batch_size=batch, chunk=chunk))
    state = init_train_state(jax.random.key(0), cfg)
    stop = jnp.int32(2**30)
    first, runs = time_call(lambda: fn(state, run_key(0), data, weights, stop), repeats=repeats)
    step_s = median(runs) / chunk
    return {"kind": "train", "preset": preset, "task": task, "batch": batch, "chunk": chunk,
            "params": count_params(state.params), "compile_s": first - median(runs),
            "ms_per_step": 1e3 * step_s, "steps_per_s": 1 / step_s,
            "sequences_per_s": batch / step_s, "runs_s": runs}


def measure_inference(preset: str, task: str, batch: int, calls: int = 200) -> dict:
    """Median milliseconds of one jitted `last_action` call on a full K-step window."""
    obs, act, horizon = SIZES[task]
    cfg = with_nominal_edges(CDTConfig.preset(preset, obs, act, horizon))
    params = init_train_state(jax.random.key(0), cfg).params
    k = cfg.seq_len
    window = {"states": jnp.ones((batch, k, obs)), "actions": jnp.zeros((batch, k, act)),
              "returns_to_go": jnp.full((batch, k), 2.0), "costs_to_go": jnp.full((batch, k), 30.0),
              "timesteps": jnp.broadcast_to(jnp.arange(k) + 100, (batch, k)),
              "mask": jnp.ones((batch, k))}
    fn = jax.jit(lambda p, w: last_action(p, cfg, w))

    def many():  # `calls` back-to-back calls, as a rollout makes them (each waits for the last)
        for _ in range(calls):
            out = jax.block_until_ready(fn(params, window))
        return out

    _, runs = time_call(many, repeats=3)
    return {"kind": "inference", "preset": preset, "task": task, "batch": batch,
            "ms_per_call": 1e3 * median(runs) / calls, "runs_s": runs}


def main() -> None:
    """Runs the sweep, prints the tables, writes JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="osrl:64,256,2048;cpu:32,64,128",
                    help="'preset:batch,batch;preset:...', run for every task")
    ap.add_argument("--tasks", default="CarGoal")
    ap.add_argument("--infer-batches", default="1,15")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--work", type=int, default=4096, help="sequences per timed call")
    ap.add_argument("--out", default="benchmarks/results/train_throughput.json")
    args = ap.parse_args()
    load_before = os.getloadavg()
    results = []
    runs = [(p, [int(b) for b in bs.split(",")]) for p, bs in
            (item.split(":") for item in args.runs.split(";"))]
    for preset, batches in runs:
        for task in args.tasks.split(","):
            for batch in batches:
                try:
                    r = measure_train(preset, task, batch, args.repeats, args.work)
                except (MemoryError, RuntimeError) as e:  # XLA out-of-memory is a RuntimeError
                    print(f"{preset} {task} batch {batch}: skipped ({type(e).__name__})")
                    continue
                results.append(r)
                print(f"{preset:5s} {task:10s} batch {batch:5d}: {r['steps_per_s']:8.2f} "
                      f"updates/s, {r['sequences_per_s']:8.0f} seq/s (compile "
                      f"{r['compile_s']:.1f} s)", flush=True)
            for batch in (int(b) for b in args.infer_batches.split(",") if b):
                r = measure_inference(preset, task, batch)
                results.append(r)
                print(f"{preset:5s} {task:10s} inference batch {batch:3d}: "
                      f"{r['ms_per_call']:.3f} ms", flush=True)
    train_rows = [
        [r["preset"], r["task"], f"{r['params']:,}", r["batch"], f"{r['steps_per_s']:.2f}",
         f"{r['sequences_per_s']:,.0f}", f"{r['ms_per_step']:.1f}", f"{r['compile_s']:.0f}",
         f"{OSRL_TORCH_MS[r['batch']] / r['ms_per_step']:.1f}x"
         if r["batch"] in OSRL_TORCH_MS and r["preset"] == "osrl" else "-"]
        for r in results if r["kind"] == "train"]
    infer_rows = [
        [r["preset"], r["task"], r["batch"], f"{r['ms_per_call']:.3f}",
         f"{OSRL_TORCH_INFER_MS[r['batch']] / r['ms_per_call']:.1f}x"
         if r["batch"] in OSRL_TORCH_INFER_MS and r["preset"] == "osrl" else "-"]
        for r in results if r["kind"] == "inference"]
    tables = [
        markdown_table(["preset", "task", "params", "batch", "updates/s", "sequences/s",
                        "ms/update", "compile s", "vs OSRL torch (1 thread)"], train_rows),
        markdown_table(["preset", "task", "batch", "ms per last_action", "vs OSRL torch"],
                       infer_rows),
    ]
    print("\nCDT training (median of repeats; windows sampled on the device, dropout on)\n")
    print(tables[0])
    print("\nInference: one jitted last_action on a full K-step window\n")
    print(tables[1])
    write_json(args.out, {"machine": {**machine(), "loadavg_before": load_before,
                                      "loadavg_after": os.getloadavg()},
                          "results": results, "tables": tables,
                          "reference_osrl_torch_ms": OSRL_TORCH_MS,
                          "reference_osrl_torch_infer_ms": OSRL_TORCH_INFER_MS})


if __name__ == "__main__":
    main()
