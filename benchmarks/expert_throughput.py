"""PPO-Lagrangian training throughput against env-only rollouts, and two ways to reset.

    python -m benchmarks.expert_throughput [--task CarGoal1] [--envs 64,256,1024] [--repeats 2]
        [--omnisafe] [--omnisafe-steps 4000] [--omnisafe-threads 2]

For each batch size, in the same run (alternated, median of `repeats`):
- `train`: one training round of the `cpu` expert preset (every env drives one whole episode,
  rollouts of 125 steps, one PPO update of 10 epochs x the preset's 8 minibatches after each, or
  `--minibatches`);
- `rollout, sync reset`: the same episode under the same policy, no updates (what training
  costs at least): all envs reset together at the episode boundary;
- `rollout, auto-reset`: the same steps with a Brax-style auto-reset, a per-step select over the
  whole env state between the stepped state and a cached initial one.
Env steps/s = envs x episode length / seconds. With `--omnisafe`, OmniSafe 0.5.0's PPOLag
(default config, one env, torch on `--omnisafe-threads` threads) trains on native
Safety-Gymnasium's same task in the `osrl` peer venv (`benchmarks/peers/omnisafe_ppolag.py`),
alternated with our cells: one epoch of `--omnisafe-steps` steps, its rollout and update.
Writes benchmarks/results/expert_throughput.{json,md}.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp

from benchmarks.common import machine, markdown_table, median, write_json, write_markdown


def _programs(task: str, n_envs: int, minibatches: int | None):
    from safecdt_jax import envs
    from safecdt_jax.experts import CostSchedule, expert_preset, make_train

    cfg = expert_preset("cpu", task=task, num_envs=n_envs, steps=1)
    cfg = cfg.replace(minibatches=minibatches) if minibatches else cfg
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


def omnisafe_run(task: str, steps: int, threads: int) -> dict:
    """One OmniSafe PPOLag epoch of `steps` env steps in the `osrl` peer venv; its timings."""
    import json
    import subprocess
    import tempfile

    from benchmarks.peers.setup import venv_python

    python = venv_python("osrl")
    if not python.exists():
        raise SystemExit("no osrl peer venv: run `python -m benchmarks.peers.setup` first")
    script = Path(__file__).resolve().parent / "peers" / "omnisafe_ppolag.py"
    with tempfile.TemporaryDirectory() as tmp:
        req, out = Path(tmp) / "request.json", Path(tmp) / "out.json"
        req.write_text(json.dumps({"task": task, "steps": steps, "envs": 1, "threads": threads}))
        proc = subprocess.run([str(python), str(script), str(req), str(out)],
                              capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(f"OmniSafe PPOLag failed:\n{proc.stderr[-3000:]}")
        return json.loads(out.read_text())


def main() -> None:
    """Times every (batch, program) cell and writes the table and the JSON."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="CarGoal1")
    ap.add_argument("--envs", default="64,256,1024")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--minibatches", type=int, default=0,
                    help="minibatches per epoch (0: the cpu preset's)")
    ap.add_argument("--omnisafe", action="store_true", help="also time OmniSafe's PPOLag")
    ap.add_argument("--omnisafe-steps", type=int, default=4000)
    ap.add_argument("--omnisafe-threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/expert_throughput.json"))
    args = ap.parse_args()
    batches = [int(x) for x in args.envs.split(",")]
    from safecdt_jax.experts import expert_preset
    cfg_minibatches = args.minibatches or expert_preset("cpu").minibatches
    programs = {}
    for n in batches:
        programs[n] = _programs(args.task, n, args.minibatches)
        for fn in programs[n][0].values():
            jax.block_until_ready(fn())  # compile
    times = {n: {k: [] for k in programs[n][0]} for n in batches}
    peer = []
    for _ in range(args.repeats):  # alternated: every cell of ours, then OmniSafe
        for n in batches:
            for name, fn in programs[n][0].items():
                t = time.perf_counter()
                jax.block_until_ready(fn())
                times[n][name].append(time.perf_counter() - t)
        if args.omnisafe:
            peer.append(omnisafe_run(args.task, args.omnisafe_steps, args.omnisafe_threads))
            print(f"OmniSafe: {peer[-1]}", flush=True)
    omni = median([p["steps"] / p["seconds"] for p in peer]) if peer else None
    rows, cells = [], []
    for n in batches:
        horizon = programs[n][1]
        rate = {k: n * horizon / median(v) for k, v in times[n].items()}
        cells.append({"envs": n, "seconds": times[n], "steps_per_s": rate})
        rows.append([n, *[f"{rate[k]:,.0f}" for k in rate],
                     f"{rate['train'] / rate['rollout, sync reset']:.2f}",
                     f"{rate['rollout, auto-reset'] / rate['rollout, sync reset']:.2f}"]
                    + ([f"{rate['train'] / omni:.0f}x"] if omni else []))
        print(f"envs {n}: " + ", ".join(f"{k} {v:,.0f}" for k, v in rate.items()), flush=True)
    head = ["envs", "train", "rollout, sync reset", "rollout, auto-reset", "train / rollout",
            "auto / sync"] + (["train / OmniSafe"] if omni else [])
    text = markdown_table(head, rows)
    if omni:
        text += (f"\n\nOmniSafe 0.5.0 PPOLag on Safety-Gymnasium {args.task} (1 env, torch "
                 f"{args.omnisafe_threads} threads, median of {len(peer)}): {omni:,.0f} env "
                 "steps/s training.")
    command = "python -m benchmarks.expert_throughput " + " ".join(sys.argv[1:])
    write_json(args.out, {"machine": machine(), "task": args.task, "cells": cells,
                          "omnisafe": {"runs": peer, "steps_per_s": omni,
                                       "threads": args.omnisafe_threads} if peer else None,
                          "minibatches": cfg_minibatches, "command": command})
    write_markdown(args.out.with_suffix(".md"), "PPO-Lagrangian training throughput", command,
                   f"Env steps/s on {args.task}, `cpu` expert preset, 10 epochs x "
                   f"{cfg_minibatches} minibatches per update, median of "
                   f"{args.repeats}, alternated.\n\n{text}")
    print(text)


if __name__ == "__main__":
    main()
