"""What a deployed CDT pays for, term by term: hazards, vase contact, vase velocity.

    python -m experiments.cost_terms [--pair CG1-CG2] [--ckpt-seeds 0,1,2] [--ratios 0.2,1.0]
        [--episodes 32] [--budget 30] [--full-episodes] [--native] [--out PATH]

For each pretrained checkpoint of the pair's `cpu` CDT (the cache's `TASK-cpu` and its
`-seedK` siblings, as `safecdt-jax paper` makes them) and each fixed cost ratio CR: zero-shot
episodes in the source and in the target task with CTG = CR x B and RTG = 0.5 x the data's
reference return (Table 5's protocol), the same layouts for every ratio. Per (task, CR): the
mean episode cost and, per cost term, the mean number of steps at which that term cost (terms
overlap, so they may sum to more than the cost), mean over checkpoints x episodes with the
spread between checkpoints. Episodes end at the first step over B unless `--full-episodes`.
With `--native`, the same CDTs also drive native Safety-Gymnasium's target task (its envs
stepped in lockstep in the peer venv, `benchmarks/peers/native_serve.py`; the model in JAX
here), so a cost term that differs between the simulators under the deployed policy shows.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from benchmarks.common import machine, markdown_table, write_json, write_markdown

RR = 0.5  # Table 5's return ratio


def checkpoints(task: str, seeds: list[int]) -> list[Path]:
    """The cache's `cpu` checkpoints of `task` for pretraining seeds `seeds` (0: `TASK-cpu`)."""
    from safecdt_jax.paths import checkpoint_dir
    from safecdt_jax.pretrain.seeds import default_outs

    out = [checkpoint_dir(task, "cpu") if s == 0 else default_outs(task, "cpu", [s])[0]
           for s in seeds]
    for path in out:
        if not path.is_dir():
            raise SystemExit(f"no checkpoint {path}: run `safecdt-jax paper` (or `run`) first")
    return out


def episodes_per_term(ckpts: list[Path], task: str, ratios: list[float], n: int,
                      budget: float, stop: bool, seed: int) -> list[dict[str, np.ndarray]]:
    """Per checkpoint, per cost ratio x episode: `return`, `cost` and each term's cost steps
    ([ratios, n]); one compiled program for every checkpoint (they share a model config)."""
    import jax
    import jax.numpy as jnp

    from safecdt_jax.deploy.job import load_deployment
    from safecdt_jax.deploy.rollout import cdt_episode

    loaded = [load_deployment(c, task) for c in ckpts]
    env, env_params, first, _, r_ref = loaded[0]

    def one(params, key, ctg):
        ep = cdt_episode(key, env, env_params, params, first.cfg, RR * r_ref, ctg,
                         stop_cost=budget if stop else None, cost_terms=True)
        return {"return": ep["return"], "cost": ep["cost"], **ep["cost_terms"]}

    keys = jax.random.split(jax.random.key(seed), n)
    run = jax.jit(jax.vmap(jax.vmap(one, (None, 0, None)), (None, None, 0)))
    ctgs = jnp.asarray(ratios, jnp.float32) * budget
    return [{k: np.asarray(v, np.float64) for k, v in run(policy.params, keys, ctgs).items()}
            for _, _, policy, _, _ in loaded]


def native_episodes_per_term(ckpts: list[Path], task: str, ratios: list[float], n: int,
                             budget: float, stop: bool, seed: int
                             ) -> list[dict[str, np.ndarray]]:
    """`episodes_per_term` with the CDT acting in native Safety-Gymnasium's `task`: env j of
    ratio i resets with seed `seed + j` (native layouts, the same for every ratio and
    checkpoint); the same context, target and runtime-budget bookkeeping as `cdt_episode`."""
    import json
    import subprocess

    import jax
    import jax.numpy as jnp

    from benchmarks.peers.setup import venv_python
    from safecdt_jax.deploy.job import load_deployment
    from safecdt_jax.deploy.rollout import context_action, context_init, context_push

    python = venv_python("safety-gymnasium")
    if not python.exists():
        raise SystemExit("no peer venv: run `python -m benchmarks.peers.setup` first")
    serve = Path(__file__).resolve().parents[1] / "benchmarks" / "peers" / "native_serve.py"
    loaded = [load_deployment(c, task) for c in ckpts]
    env, _, first, _, r_ref = loaded[0]
    cfg, m = first.cfg, len(ratios) * n

    def act(params, ctx, obs, rtg, ctg, t, key):
        ctx = context_push(ctx, obs, rtg * cfg.reward_scale, ctg * cfg.cost_scale, t)
        action = context_action(params, cfg, ctx, jax.random.fold_in(key, t + 1))
        return action, ctx._replace(actions=ctx.actions.at[-1].set(action))

    step = jax.jit(jax.vmap(act, (None, 0, 0, 0, 0, None, 0)))
    keys = jnp.tile(jax.random.split(jax.random.key(seed), n), (len(ratios),))
    out = []
    for _, _, policy, _, _ in loaded:
        proc = subprocess.Popen([str(python), str(serve), task, str(seed), str(m)], text=True,
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        obs = np.asarray(json.loads(proc.stdout.readline())["obs"], np.float32)
        ctx = jax.vmap(lambda _: context_init(cfg))(jnp.arange(m))
        rtg = np.full(m, RR * r_ref, np.float32)
        ctg = np.repeat(np.asarray(ratios, np.float32) * budget, n)
        alive, spent = np.ones(m, bool), np.zeros(m)
        ret, cost = np.zeros(m), np.zeros(m)
        terms: dict[str, np.ndarray] = {}
        for t in range(env.episode_length):
            action, ctx = step(policy.params, ctx, jnp.asarray(obs), jnp.asarray(rtg),
                               jnp.asarray(ctg), t, keys)
            proc.stdin.write(json.dumps({"actions": np.asarray(action).tolist()}) + "\n")
            proc.stdin.flush()
            got = json.loads(proc.stdout.readline())
            r, c = np.asarray(got["reward"]) * alive, np.asarray(got["cost"]) * alive
            ret, cost, spent = ret + r, cost + c, spent + c
            for k, v in got["terms"].items():
                terms[k] = terms.get(k, np.zeros(m)) + np.asarray(v) * alive
            if not cfg.constant_targets:
                rtg = (rtg - r).astype(np.float32)
                ctg = np.maximum(ctg - c, 0.0).astype(np.float32)
            alive &= ~np.asarray(got["done"], bool) & ((not stop) | (spent <= budget))
            obs = np.asarray(got["obs"], np.float32)
        proc.stdin.close()
        proc.wait()
        present = [k for k in env.task.cost_terms() if k in terms]
        out.append({k: v.reshape(len(ratios), n) for k, v in
                    {"return": ret, "cost": cost, **{k: terms[k] for k in present}}.items()})
    return out


def main(argv: list[str] | None = None) -> None:
    from safecdt_jax.pairs import parse_pair

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", default="CG1-CG2")
    ap.add_argument("--ckpt-seeds", default="0,1,2")
    ap.add_argument("--ratios", default="0.2,1.0")
    ap.add_argument("--episodes", type=int, default=32)
    ap.add_argument("--budget", type=float, default=30.0)
    ap.add_argument("--full-episodes", action="store_true")
    ap.add_argument("--native", action="store_true",
                    help="also run the target task in native Safety-Gymnasium")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/cost_terms.json"))
    args = ap.parse_args(argv)
    source, target = parse_pair(args.pair)
    ratios = [float(r) for r in args.ratios.split(",")]
    ckpts = checkpoints(source, [int(s) for s in args.ckpt_seeds.split(",")])
    rows = []
    runs = [(source, "ours"), (target, "ours")] + [(target, "native")] * args.native
    for task, sim in runs:
        measure = native_episodes_per_term if sim == "native" else episodes_per_term
        per_ckpt = measure(ckpts, task, ratios, args.episodes, args.budget,
                           not args.full_episodes, args.seed)
        for i, cr in enumerate(ratios):
            row = {"task": task, "sim": sim, "cr": cr}
            for k in per_ckpt[0]:
                means = [float(m[k][i].mean()) for m in per_ckpt]
                row[k] = {"mean": float(np.mean(means)), "ckpt_std": float(np.std(means)),
                          "per_ckpt": means}
            rows.append(row)
        print(f"{task} ({sim}): done", file=sys.stderr, flush=True)
    terms = [k for k in rows[0] if k.startswith("cost_")]
    command = "python -m experiments.cost_terms " + " ".join(sys.argv[1:] if argv is None
                                                             else argv)
    write_json(args.out, {"command": command, "machine": machine(), "pair": args.pair,
                          "checkpoints": [str(c) for c in ckpts], "episodes": args.episodes,
                          "budget": args.budget, "stop_over_budget": not args.full_episodes,
                          "rr": RR, "rows": rows})
    fmt = lambda s: f"{s['mean']:.2f} ({s['ckpt_std']:.2f})"
    body = markdown_table(
        ["task", "sim", "CR", "return", "cost", *(t.removeprefix("cost_") for t in terms)],
        [[r["task"], r["sim"], f"{r['cr']:g}", fmt(r["return"]), fmt(r["cost"]),
          *(fmt(r[t]) for t in terms)] for r in rows])
    body += (f"\n\nper episode: mean over {len(ckpts)} checkpoints x {args.episodes} episodes "
             f"(std between the checkpoints' means); a term's column counts the steps at which "
             f"that term cost. Episodes "
             f"{'run to the time limit' if args.full_episodes else 'end at the first step over B'}"
             f", B = {args.budget:g}, RTG = {RR} x the reference return.\n")
    write_markdown(args.out.with_suffix(".md"), f"Cost terms of the zero-shot CDT, {args.pair}",
                   command, body)
    print(args.out.with_suffix(".md").read_text())


if __name__ == "__main__":
    main()
