"""The seeds' LoRA steps: batched (one product over every seed), in turn (one seed at a time),
and in passes of a few windows.

    python -m benchmarks.lora_in_turn [--task CarGoal2] [--preset cpu] [--seeds 15]
        [--episodes 3] [--repeats 3] [--threads 0] [--modes batched,turn]

A mode is `batched` or `turn` (`DeployConfig.lora_in_turn` off / on), optionally with `/M`, the
pass size `DeployConfig.lora_micro_batch` (e.g. `turn/8`: each seed's 32 windows in turn, in
passes of 8). Two measurements, each alternated (one call per mode in turn) and reported as
medians:
- `gradient`: the adapter gradient of one LoRA step (32 windows per seed, `--preset`) for
  `--seeds` seeds, `jit(vmap(...))` as the deployment computes it, and the largest difference
  of each mode's result from the first mode's;
- `deployment`: the full Safe-CDT sweep (rollouts, 10 LoRA steps per episode, the scheduler)
  of `--seeds` seeds x `--episodes` episodes per mode, and the largest difference in the
  episodes' returns and costs (float rounding in the adapters can move a rollout once a LoRA
  step has run). A program with one LoRA step per episode (first mode) gives each mode's LoRA
  share of the sweep: (10 steps - 1 step) x 10 / 9.
Random weights of the `--preset` CDT (the cost does not depend on them). Writes `--out`
(default benchmarks/results/lora_in_turn.{json,md}).
"""

import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.common import (
    machine,
    markdown_table,
    median,
    pin_threads,
    write_json,
    write_markdown,
)

OUT = "benchmarks/results/lora_in_turn.json"
DEFAULT_STEPS = 10  # DeployConfig().lora_steps


def alternate(calls: dict, repeats: int) -> dict[str, list[float]]:
    """Seconds of each no-argument call, `repeats` rounds in turn (the first round compiles
    and is not counted)."""
    times = {name: [] for name in calls}
    for i in range(repeats + 1):
        for name, call in calls.items():
            t = time.perf_counter()
            jax.block_until_ready(call())
            if i:
                times[name].append(time.perf_counter() - t)
    return times


def max_diff(a, b) -> float:
    """Largest absolute difference over the leaves of two pytrees of arrays."""
    return max(float(jnp.abs(jnp.asarray(x, jnp.float32) - jnp.asarray(y, jnp.float32)).max())
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def parse_mode(mode: str) -> dict:
    """`batched`, `turn`, `batched/M` or `turn/M` -> DeployConfig overrides."""
    kind, _, passes = mode.partition("/")
    if kind not in ("batched", "turn"):
        raise SystemExit(f"unknown mode {mode!r}: use batched, turn, batched/M or turn/M")
    return {"lora_in_turn": kind == "turn", "lora_micro_batch": int(passes or 0)}


def gradient(task: str, preset: str, seeds: int, repeats: int, modes: list[str]) -> dict:
    """One LoRA step's adapter gradient for `seeds` seeds, per mode."""
    from benchmarks.deploy_throughput import setup
    from benchmarks.train_throughput import synthetic_data
    from safecdt_jax.data import sample_windows
    from safecdt_jax.deploy import adapter_gradient, init_adapters, seed_keys

    _, _, model_cfg, base, cfg, _ = setup(task, preset, 1)
    data = synthetic_data(model_cfg.obs_dim, model_cfg.act_dim, model_cfg.episode_len)
    keys = seed_keys(0, seeds)
    lora = init_adapters(keys, base, model_cfg)
    windows = jax.vmap(lambda k: sample_windows(
        k, data, cfg.lora_batch, model_cfg.seq_len, None, model_cfg.reward_scale,
        model_cfg.cost_scale))(keys)
    weights = jnp.ones((seeds, cfg.lora_batch))

    def program(lora_in_turn, lora_micro_batch):
        def grad(lo, win, w):
            return adapter_gradient(lo, base, model_cfg, win, w, None, lora_micro_batch)
        return jax.jit(jax.vmap(jax.custom_batching.sequential_vmap(grad) if lora_in_turn
                                else grad))

    progs = {m: program(**parse_mode(m)) for m in modes}
    outs = {k: f(lora, windows, weights) for k, f in progs.items()}
    times = alternate({k: (lambda f=f: f(lora, windows, weights)) for k, f in progs.items()},
                      repeats)
    return {"ms": {k: 1e3 * median(v) for k, v in times.items()},
            "max_abs_diff": {k: max_diff(outs[modes[0]], v) for k, v in outs.items()}}


def deployment(task: str, preset: str, seeds: int, episodes: int, repeats: int,
               modes: list[str]) -> dict:
    """The Safe-CDT sweep of `seeds` x `episodes` per mode, and each mode's LoRA share."""
    from benchmarks.deploy_throughput import setup
    from safecdt_jax.deploy import init_adapters, seed_keys, stack_specs
    from safecdt_jax.deploy.sweep import _compiled

    env, params, model_cfg, base, cfg, spec = setup(task, preset, episodes)
    keys, specs = seed_keys(0, seeds), stack_specs([spec])
    lora = init_adapters(keys, base, model_cfg)
    index = np.arange(episodes, dtype=np.int32)
    one_step = f"{modes[0]}, 1 LoRA step"
    cfgs = {m: cfg.replace(**parse_mode(m)) for m in modes}
    cfgs[one_step] = cfgs[modes[0]].replace(lora_steps=1)
    progs = {k: _compiled(env, model_cfg, c, False, True) for k, c in cfgs.items()}

    def call(init_all, run_all):
        return run_all(init_all(keys, lora, specs), index, base, params, specs)[1]

    metrics = {k: jax.device_get(call(*p)) for k, p in progs.items()}
    times = alternate({k: (lambda p=p: call(*p)) for k, p in progs.items()}, repeats)
    diff = {k: {f: float(np.abs(getattr(metrics[modes[0]], f) - getattr(metrics[k], f)).max())
                for f in ("returns", "costs")} for k in modes}
    s = {k: median(v) for k, v in times.items()}
    # The LoRA steps' share: what 9 more steps per episode add, scaled to all 10.
    steps = cfg.lora_steps
    lora_s = {k: (s[k] - s[one_step]) * steps / (steps - 1) for k in modes}
    return {"s": s, "max_abs_diff": diff, "lora_s": lora_s,
            "per_episode_s": {k: v / episodes for k, v in s.items()}}


def main() -> None:
    """Runs both measurements, prints the table, writes JSON and markdown."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal2")
    ap.add_argument("--preset", default="cpu", help="CDT size preset: cpu, osrl or paper")
    ap.add_argument("--seeds", type=int, default=15)
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="1: XLA on one thread; 0: default")
    ap.add_argument("--modes", default="batched,turn",
                    help="comma-separated; the first is the baseline of speedups and diffs")
    ap.add_argument("--deploy-modes", default=None,
                    help="modes of the deployment measurement (default: --modes)")
    ap.add_argument("--out", default=OUT)
    args = ap.parse_args()
    if args.threads:
        pin_threads(args.threads)
    modes = args.modes.split(",")
    deploy_modes = args.deploy_modes.split(",") if args.deploy_modes else modes
    for m in {*modes, *deploy_modes}:
        parse_mode(m)
    g = gradient(args.task, args.preset, args.seeds, args.repeats, modes)
    print(g, flush=True)
    d = deployment(args.task, args.preset, args.seeds, args.episodes, args.repeats,
                   deploy_modes)
    print(d, flush=True)
    base_g, base_d = g["ms"][modes[0]], d["s"][deploy_modes[0]]
    base_l = d["lora_s"][deploy_modes[0]]
    rows = [[f"adapter gradient, {args.seeds} seeds x 32 windows", m, f"{g['ms'][m]:.1f} ms",
             f"{base_g / g['ms'][m]:.2f}x", f"{g['max_abs_diff'][m]:.1e}"] for m in modes]
    for m in deploy_modes:
        diff = d["max_abs_diff"][m]
        rows.append([f"Safe-CDT sweep, {args.seeds} seeds x {args.episodes} episodes", m,
                     f"{d['s'][m]:.1f} s", f"{base_d / d['s'][m]:.2f}x",
                     f"returns {diff['returns']:.2g}, costs {diff['costs']:.2g}"])
        rows.append([f"of which the {DEFAULT_STEPS} LoRA steps per episode", m,
                     f"{d['lora_s'][m]:.1f} s", f"{base_l / d['lora_s'][m]:.2f}x", ""])
    table = markdown_table(["measurement", "mode", "time", "speedup", "largest difference"],
                           rows)
    print(table)
    command = "python -m benchmarks.lora_in_turn " + " ".join(sys.argv[1:])
    write_json(args.out, {"machine": machine(), "args": vars(args), "gradient": g,
                          "deployment": d, "command": command})
    write_markdown(args.out.removesuffix(".json") + ".md",
                   "The seeds' LoRA steps: batched, in turn, in passes", command,
                   f"{args.task}, `{args.preset}` preset, random weights, XLA threads: "
                   f"{args.threads or 'default'}; medians of {args.repeats} alternated calls. "
                   "Speedups and differences against the first mode. `turn`: "
                   "`lora_in_turn`; `/M`: `lora_micro_batch` M.\n\n" + table)


if __name__ == "__main__":
    main()
