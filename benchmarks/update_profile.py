"""Where one CDT update's time goes: the update taken apart, piece by piece, at each batch size.

    python -m benchmarks.update_profile [--preset osrl] [--batches 64,256,2048] [--repeats 5]
        [--threads 1] [--osrl] [--no-pieces] [--micro-batch 64,256]

Each row is one jitted program timed on its own (median of `repeats` calls after compiling),
on synthetic CarGoal-sized episodes (`benchmarks.train_throughput.synthetic_data`):
- `update`: one whole pretraining update, as `train_chunk` runs it (window sampling, forward,
  backward, AdamW + temperature step, dropout on);
- `update, no dropout`: the same with the three dropout rates at 0 (no mask noise drawn);
- `forward + backward`: `value_and_grad(cdt_loss)` on a fixed batch, dropout on;
- `forward + backward, no dropout`; `forward`: the loss alone, dropout on;
- `dropout noise`: the random draw of every mask of one forward (`_dropout_noise`);
- `window sampling`: `sample_windows` alone; `optimizer`: clip + AdamW on param-shaped grads.
With `--osrl`, OSRL's own `CDTTrainer.train_one_step` (PyTorch, the `osrl` peer venv, the same
thread count and cores) on a fixed batch, alternated with our `update`, and the speedup
(median OSRL / median ours). `--no-pieces` times only the whole update (and OSRL).
`--micro-batch M[,M2...]` adds `update, passes of <= M` for each M: the same update with its
gradient summed over passes of at most M windows (`PretrainConfig.micro_batch`), alternated with
OSRL's too.
Also XLA's own count (`cost_analysis`) of the update's FLOPs and bytes, and the GFLOP/s.
With `--threads N` XLA runs on N threads pinned to N cores (`benchmarks.common.pin_threads`, as
BENCHMARKS.md's peer comparison; OSRL's reference times are one thread's).
Writes benchmarks/results/update_profile.{json,md}.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from benchmarks.common import (
    machine,
    markdown_table,
    median,
    pin_threads,
    time_call,
    write_json,
    write_markdown,
)

OUT = Path("benchmarks/results/update_profile.json")


def passes_name(micro_batch: int) -> str:
    """The program name of the update in passes of at most `micro_batch` windows."""
    return f"update, passes of <= {micro_batch}"


def is_update(name: str) -> bool:
    """Whether program `name` is a whole update (what is timed against OSRL's step)."""
    return name == "update" or name.startswith("update, passes")


def programs(preset: str, batch: int, micro_batches_: tuple[int, ...] = ()) -> dict:
    """Name -> (jitted fn, args) for every piece of one update at `batch` (and, for each size
    in `micro_batches_` that splits the batch, the update in passes of at most that many)."""
    from benchmarks.train_throughput import SIZES, synthetic_data
    from safecdt_jax.data import sample_windows
    from safecdt_jax.model import CDTConfig, OptimConfig, init_train_state, with_nominal_edges
    from safecdt_jax.model.cdt import _dropout_noise, _dropout_shapes
    from safecdt_jax.model.loss import cdt_loss
    from safecdt_jax.model.optim import make_optimizer, micro_batches
    from safecdt_jax.pretrain import PretrainConfig
    from safecdt_jax.pretrain.loop import make_update

    obs, act, horizon = SIZES["CarGoal"]
    cfg = with_nominal_edges(CDTConfig.preset(preset, obs, act, horizon))
    quiet = cfg.replace(embedding_dropout=0.0, attention_dropout=0.0, residual_dropout=0.0)
    data = synthetic_data(obs, act, horizon)
    weights = jnp.full(data.lengths.shape, 1.0 / data.lengths.shape[0])
    pre = PretrainConfig(batch_size=batch)
    state = init_train_state(jax.random.key(0), cfg)
    key = jax.random.key(1)

    def windows(k):
        return sample_windows(k, data, batch, cfg.seq_len, weights,
                              reward_scale=cfg.reward_scale, cost_scale=cfg.cost_scale)._asdict()

    fixed = jax.jit(windows)(key)

    def update(c):
        return jax.jit(make_update(c, OptimConfig(), pre))

    def grad(c):
        return jax.jit(lambda p, b, k: jax.value_and_grad(cdt_loss, has_aux=True)(
            p, state.log_temperature, c, b, k))

    txs = make_optimizer(OptimConfig())
    shapes = _dropout_shapes(cfg, batch, cfg.seq_len)
    split = {passes_name(m): (jax.jit(make_update(cfg, OptimConfig(), pre.replace(micro_batch=m))),
                              (state, key, data, weights))
             for m in micro_batches_ if micro_batches(batch, m) > 1}
    return {
        "update": (update(cfg), (state, key, data, weights)),
        **split,
        "update, no dropout": (update(quiet), (state, key, data, weights)),
        "forward + backward": (grad(cfg), (state.params, fixed, key)),
        "forward + backward, no dropout": (grad(quiet), (state.params, fixed, key)),
        "forward": (jax.jit(lambda p, b, k: cdt_loss(p, state.log_temperature, cfg, b, k)[0]),
                    (state.params, fixed, key)),
        "dropout noise": (jax.jit(lambda k: _dropout_noise(k, shapes)), (key,)),
        "window sampling": (jax.jit(windows), (key,)),
        "optimizer": (jax.jit(lambda g, s, p: txs.model.update(g, s, p)[0]),
                      (state.params, state.opt_state, state.params)),
    }


# Op families of the breakdown: the first family whose keyword occurs in an op's JAX op name
# (HLO metadata) takes it; matrix products are told by the HLO instruction itself.
FAMILIES = (
    ("window sampling", ("sample_windows", "gather", "dynamic_slice")),
    # threefry runs as a while loop over its rounds; its fusions carry the loop's op names
    ("dropout RNG", ("threefry", "random", "_uniform", "_randint", "bitcast_convert_type",
                     "iota_2x32", "/while", "closed_call", "/xor", "shift_left", "shift_right")),
    ("GELU", ("erf", "gelu")),
    ("attention softmax, mask, head transposes", ("/attn/",)),
    ("LayerNorm", ("/ln1/", "/ln2/", "embed_norm", "out_norm", "layer_norm")),
    ("optimizer", ("adam", "clip_by_global_norm", "optax", "apply_updates", "global_norm")),
)


def op_breakdown(fn, args, calls: int = 3) -> dict[str, float]:
    """Milliseconds per call by op family, from a `jax.profiler` trace of `calls` calls.

    XLA:CPU traces every executed HLO instruction (thunk); each is put in a family by its
    instruction (matrix products: `dot` and YNNPACK fusions) or by the JAX op name in its
    metadata (`FAMILIES`), the rest is `other elementwise`.
    """
    import collections
    import glob
    import gzip
    import json
    import re

    compiled = fn.lower(*args).compile()
    meta = dict(re.findall(r"%([\w.\-]+) = .*?op_name=\"([^\"]*)\"", compiled.as_text()))
    jax.block_until_ready(fn(*args))
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp, create_perfetto_trace=True):
            for _ in range(calls):
                jax.block_until_ready(fn(*args))
        trace = glob.glob(f"{tmp}/**/perfetto_trace.json.gz", recursive=True)[0]
        events = json.load(gzip.open(trace))
    events = events["traceEvents"] if isinstance(events, dict) else events
    out: dict[str, float] = collections.Counter()
    for e in events:
        name = e.get("name", "")
        if e.get("ph") != "X" or name not in meta:
            continue
        op = meta[name]
        if name.startswith(("dot", "ynn_fusion")):
            family = "matrix products"
        else:
            family = next((f for f, keys in FAMILIES if any(k in op for k in keys)),
                          "other elementwise")
        out[family] += e.get("dur", 0.0) / 1e3 / calls
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def xla_cost(fn, args) -> dict:
    """XLA's FLOP and byte counts of one compiled program."""
    cost = fn.lower(*args).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return {"gflop": cost.get("flops", 0.0) / 1e9,
            "gbytes": cost.get("bytes accessed", 0.0) / 1e9}


def main() -> None:
    """Times every piece at every batch and writes the table and the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="osrl")
    ap.add_argument("--batches", default="64,256,2048")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=0, help="1: XLA on one thread; 0: default")
    ap.add_argument("--osrl", action="store_true", help="also time OSRL's train_one_step")
    ap.add_argument("--micro-batch", default="",
                    help="also time the update in passes of at most M windows, for each M of "
                         "this comma list")
    ap.add_argument("--no-pieces", dest="pieces", action="store_false",
                    help="time the whole update only")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    if args.threads:
        pin_threads(args.threads)
    peer = None
    if args.osrl:
        from benchmarks.run_all import Peer, dims

        peer = Peer("osrl", Path(tempfile.gettempdir()) / "update_profile_osrl.log")
    micro = tuple(int(m) for m in args.micro_batch.split(",") if m)
    cells, rows, fam_rows, vs_rows = [], [], [], []
    for batch in (int(b) for b in args.batches.split(",")):
        progs = programs(args.preset, batch, micro)
        if not args.pieces:
            progs = {k: v for k, v in progs.items() if is_update(k)}
        cost = xla_cost(*progs["update"])
        families = op_breakdown(*progs["update"])
        times = {}
        for name, (fn, fargs) in progs.items():
            _, runs = time_call(lambda fn=fn, fargs=fargs: fn(*fargs), repeats=args.repeats)
            times[name] = median(runs) * 1e3
            print(f"batch {batch}: {name} {times[name]:.1f} ms", flush=True)
        cell = {"batch": batch, "ms": times, "xla": cost, "families_ms": families,
                "update_gflop_per_s": cost["gflop"] / (times["update"] / 1e3)}
        if peer is not None:  # alternated: OSRL's step, then each of our updates
            ours_names = [k for k in progs if is_update(k)]
            steps = max(1, 512 // batch)
            theirs, ours = [], {k: [] for k in ours_names}
            for _ in range(args.repeats):
                a = peer("train", batch=batch, steps=steps, **dims("CarGoal1"))
                theirs.append(1e3 * a["seconds"] / a["steps"])
                for name in ours_names:
                    fn, fargs = progs[name]
                    t = time.perf_counter()
                    jax.block_until_ready(fn(*fargs))
                    ours[name].append(1e3 * (time.perf_counter() - t))
            cell["osrl_ms"], cell["ours_alternated_ms"] = theirs, ours["update"]
            cell["speedup"] = median(theirs) / median(ours["update"])
            cell["alternated_ms"] = ours
            cell["speedups"] = {k: median(theirs) / median(v) for k, v in ours.items()}
            vs_rows += [[batch, f"{median(theirs):.1f}", k, f"{median(v):.1f}",
                         f"{cell['speedups'][k]:.2f}x"] for k, v in ours.items()]
            print(f"batch {batch}: OSRL {median(theirs):.1f} ms, ours "
                  + ", ".join(f"{k} {median(v):.1f} ms" for k, v in ours.items()), flush=True)
        cells.append(cell)
        full = times["update"]
        for name, ms in times.items():
            rows.append([batch, name, f"{ms:.1f}", f"{100 * ms / full:.0f}%"])
        rows.append([batch, "XLA count of the update", f"{cost['gflop']:.1f} GFLOP, "
                     f"{cost['gbytes']:.2f} GB", f"{cost['gflop'] / (full / 1e3):.0f} GFLOP/s"])
        traced = sum(families.values())
        fam_rows += [[batch, name, f"{ms:.1f}", f"{100 * ms / traced:.0f}%"]
                     for name, ms in families.items()]
    text = markdown_table(["batch", "program", "ms (median)", "share of the update"], rows)
    if vs_rows:
        text = ("Against OSRL (alternated, median of each side):\n\n" + markdown_table(
            ["batch", "OSRL train_one_step ms", "ours", "ms", "speedup"], vs_rows)
            + "\n\nOur update taken apart:\n\n" + text)
    text += ("\n\nThe update by op family (a `jax.profiler` trace of 3 calls; the share of the "
             "traced op time):\n\n" + markdown_table(["batch", "op family", "ms per update",
                                                    "share"], fam_rows))
    command = "python -m benchmarks.update_profile " + " ".join(sys.argv[1:])
    write_json(args.out, {"machine": machine(), "preset": args.preset, "threads": args.threads,
                          "cells": cells, "command": command})
    if peer is not None:
        peer.close()
    write_markdown(args.out.with_suffix(".md"), "Where a CDT update's time goes", command,
                   f"`{args.preset}` preset, CarGoal sizes, XLA threads: "
                   f"{args.threads or 'default'}.\n\n{text}")
    print(text)


if __name__ == "__main__":
    main()
