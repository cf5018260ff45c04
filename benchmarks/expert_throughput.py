"""PPO-Lagrangian training throughput against env-only rollouts, and two ways to reset.

    python -m benchmarks.expert_throughput [--task CarGoal1] [--envs 64,256,1024] [--repeats 2]

For each batch size, in the same run (alternated, median of `repeats`):
- `train`: one training round of the `cpu` expert preset (every env drives one whole episode,
  rollouts of 125 steps, one PPO update of 10 epochs x 8 minibatches after each);
- `rollout, sync reset`: the same episode under the same policy, no updates (what training
  costs at least): all envs reset together at the episode boundary;
- `rollout, auto-reset`: the same steps with a Brax-style auto-reset, a per-step select over the
  whole env state between the stepped state and a cached initial one.
Env steps/s = envs x episode length / seconds. Writes benchmarks/results/expert_throughput.json.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from benchmarks.common import machine, markdown_table, median, write_json


def _programs(task: str, n_envs: int):
    from safecdt_jax import envs
    from safecdt_jax.experts import CostSchedule, expert_preset, make_train

    cfg = expert_preset("cpu", task=task, num_envs=n_envs, minibatches=8, steps=1)
    train = make_train(cfg)
    env, params = envs.make(task)
    runner = jax.jit(train.init)(jax.random.PRNGKey(0))
    sched = jnp.asarray(CostSchedule(25, 25).as_array())
    snapshot = {"actor": runner.params["actor"], "norm": runner.norm}
    horizon = cfg.horizon

    train_round = jax.jit(lambda r: train.run_rounds(r, sched, 1)[1]["return"])

    def rollout(key, auto_reset: bool):
        first = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, n_envs), params)

        def step(states, k):
            a = train.policy(snapshot, states.obs, k)
            nxt = jax.vmap(env.step, in_axes=(0, 0, None))(states, a, params)
            if not auto_reset:  # one episode: nothing ends before the last step
                return nxt, nxt.reward
            done = nxt.done > 0

            def pick(x, y):
                return jnp.where(done.reshape(done.shape + (1,) * (x.ndim - 1)), x, y)

            return jax.tree.map(pick, first, nxt), nxt.reward

        return jax.lax.scan(step, first, jax.random.split(key, horizon))[1].sum()

    sync = jax.jit(lambda k: rollout(k, False))
    auto = jax.jit(lambda k: rollout(k, True))

    return {"train": lambda: train_round(runner), "rollout, sync reset":
            lambda: sync(jax.random.PRNGKey(1)), "rollout, auto-reset":
            lambda: auto(jax.random.PRNGKey(1))}, horizon


def main() -> None:
    """Times every (batch, program) cell and writes the table and the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal1")
    ap.add_argument("--envs", default="64,256,1024")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/expert_throughput.json"))
    args = ap.parse_args()
    rows, cells = [], []
    for n in (int(x) for x in args.envs.split(",")):
        progs, horizon = _programs(args.task, n)
        for fn in progs.values():
            jax.block_until_ready(fn())  # compile
        times = {k: [] for k in progs}
        for _ in range(args.repeats):  # alternated
            for name, fn in progs.items():
                t = time.perf_counter()
                jax.block_until_ready(fn())
                times[name].append(time.perf_counter() - t)
        rate = {k: n * horizon / median(v) for k, v in times.items()}
        cells.append({"envs": n, "seconds": times, "steps_per_s": rate})
        rows.append([n, *[f"{rate[k]:,.0f}" for k in progs],
                     f"{rate['train'] / rate['rollout, sync reset']:.2f}",
                     f"{rate['rollout, auto-reset'] / rate['rollout, sync reset']:.2f}"])
        print(f"envs {n}: " + ", ".join(f"{k} {v:,.0f}" for k, v in rate.items()), flush=True)
    head = ["envs", "train", "rollout, sync reset", "rollout, auto-reset", "train / rollout",
            "auto / sync"]
    text = markdown_table(head, rows)
    write_json(args.out, {"machine": machine(), "task": args.task, "cells": cells,
                          "command": "python -m benchmarks.expert_throughput"})
    args.out.with_suffix(".md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
