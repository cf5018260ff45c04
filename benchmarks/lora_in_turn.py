"""The seeds' LoRA steps batched (one product over every seed) or in turn (one seed at a time).

    python -m benchmarks.lora_in_turn [--task CarGoal2] [--seeds 15] [--episodes 3]
        [--repeats 3] [--threads 0]

Two measurements, each alternated (batched, in turn, batched, ...) and reported as medians:
- `gradient`: the adapter gradient of one LoRA step (32 windows per seed, `cpu` preset) for
  `--seeds` seeds, `jit(vmap(value_and_grad(lora_loss)))` as the deployment computes it with
  `DeployConfig.lora_in_turn` off, against the same under `sequential_vmap` (on), with the
  largest difference of the results;
- `deployment`: the full Safe-CDT sweep (rollouts, 10 LoRA steps per episode, the scheduler)
  of `--seeds` seeds x `--episodes` episodes with the flag off and on, and the largest
  difference in the episodes' returns and costs (float rounding in the adapters can move a
  rollout once a LoRA step has run).
Random `cpu`-preset weights (the cost does not depend on them). Writes
benchmarks/results/lora_in_turn.{json,md}.
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


def gradient(task: str, seeds: int, repeats: int) -> dict:
    """One LoRA step's adapter gradient for `seeds` seeds, batched vs in turn."""
    from benchmarks.deploy_throughput import setup
    from benchmarks.train_throughput import synthetic_data
    from safecdt_jax.data import sample_windows
    from safecdt_jax.deploy import init_adapters, seed_keys
    from safecdt_jax.deploy.finetune import lora_loss

    _, _, model_cfg, base, cfg, _ = setup(task, "cpu", 1)
    data = synthetic_data(model_cfg.obs_dim, model_cfg.act_dim, model_cfg.episode_len)
    keys = seed_keys(0, seeds)
    lora = init_adapters(keys, base, model_cfg)
    windows = jax.vmap(lambda k: sample_windows(
        k, data, cfg.lora_batch, model_cfg.seq_len, None, model_cfg.reward_scale,
        model_cfg.cost_scale))(keys)
    weights = jnp.ones((seeds, cfg.lora_batch))

    def grad(lo, win, w):
        return jax.value_and_grad(lora_loss)(lo, base, model_cfg, win, w)

    progs = {"batched": jax.jit(jax.vmap(grad)),
             "in turn": jax.jit(jax.vmap(jax.custom_batching.sequential_vmap(grad)))}
    outs = {k: f(lora, windows, weights) for k, f in progs.items()}
    times = alternate({k: (lambda f=f: f(lora, windows, weights)) for k, f in progs.items()},
                      repeats)
    return {"ms": {k: 1e3 * median(v) for k, v in times.items()},
            "max_abs_diff": max_diff(outs["batched"], outs["in turn"])}


def deployment(task: str, seeds: int, episodes: int, repeats: int) -> dict:
    """The Safe-CDT sweep of `seeds` x `episodes`, `lora_in_turn` off vs on."""
    from benchmarks.deploy_throughput import setup
    from safecdt_jax.deploy import init_adapters, seed_keys, stack_specs
    from safecdt_jax.deploy.sweep import _compiled

    env, params, model_cfg, base, cfg, spec = setup(task, "cpu", episodes)
    keys, specs = seed_keys(0, seeds), stack_specs([spec])
    lora = init_adapters(keys, base, model_cfg)
    index = np.arange(episodes, dtype=np.int32)
    progs = {name: _compiled(env, model_cfg, cfg.replace(lora_in_turn=on), False, True)
             for name, on in (("batched", False), ("in turn", True))}

    def call(init_all, run_all):
        return run_all(init_all(keys, lora, specs), index, base, params, specs)[1]

    metrics = {k: jax.device_get(call(*p)) for k, p in progs.items()}
    times = alternate({k: (lambda p=p: call(*p)) for k, p in progs.items()}, repeats)
    diff = {f: float(np.abs(getattr(metrics["batched"], f) - getattr(metrics["in turn"], f)).max())
            for f in ("returns", "costs")}
    return {"s": {k: median(v) for k, v in times.items()}, "max_abs_diff": diff,
            "per_episode_s": {k: median(v) / episodes for k, v in times.items()}}


def main() -> None:
    """Runs both measurements, prints the table, writes JSON and markdown."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal2")
    ap.add_argument("--seeds", type=int, default=15)
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="1: XLA on one thread; 0: default")
    ap.add_argument("--out", default=OUT)
    args = ap.parse_args()
    if args.threads:
        pin_threads(args.threads)
    g = gradient(args.task, args.seeds, args.repeats)
    print(g, flush=True)
    d = deployment(args.task, args.seeds, args.episodes, args.repeats)
    print(d, flush=True)
    table = markdown_table(
        ["measurement", "batched", "in turn", "speedup", "largest difference"],
        [[f"adapter gradient, {args.seeds} seeds x 32 windows (ms)", f"{g['ms']['batched']:.1f}",
          f"{g['ms']['in turn']:.1f}", f"{g['ms']['batched'] / g['ms']['in turn']:.2f}x",
          f"{g['max_abs_diff']:.1e}"],
         [f"Safe-CDT sweep, {args.seeds} seeds x {args.episodes} episodes (s)",
          f"{d['s']['batched']:.1f}", f"{d['s']['in turn']:.1f}",
          f"{d['s']['batched'] / d['s']['in turn']:.2f}x",
          f"returns {d['max_abs_diff']['returns']:.2g}, costs {d['max_abs_diff']['costs']:.2g}"]])
    print(table)
    command = "python -m benchmarks.lora_in_turn " + " ".join(sys.argv[1:])
    write_json(args.out, {"machine": machine(), "args": vars(args), "gradient": g,
                          "deployment": d, "command": command})
    write_markdown(args.out.removesuffix(".json") + ".md",
                   "The seeds' LoRA steps, batched or in turn", command,
                   f"{args.task}, `cpu` preset, random weights, XLA threads: "
                   f"{args.threads or 'default'}; medians of {args.repeats} alternated calls."
                   f"\n\n{table}")


if __name__ == "__main__":
    main()
