"""What a deployed CDT pays for, term by term: hazards, vase contact, vase velocity.

    python -m experiments.cost_terms [--pair CG1-CG2] [--ckpt-seeds 0,1,2] [--ratios 0.2,1.0]
        [--episodes 32] [--budget 30] [--full-episodes] [--out PATH]

For each pretrained checkpoint of the pair's `cpu` CDT (the cache's `TASK-cpu` and its
`-seedK` siblings, as `safecdt-jax paper` makes them) and each fixed cost ratio CR: zero-shot
episodes in the source and in the target task with CTG = CR x B and RTG = 0.5 x the data's
reference return (Table 5's protocol), the same layouts for every ratio. Per (task, CR): the
mean episode cost and, per cost term, the mean number of steps at which that term cost (terms
overlap, so they may sum to more than the cost), mean over checkpoints x episodes with the
spread between checkpoints. Episodes end at the first step over B unless `--full-episodes`.
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

    first = checkpoint_dir(task, "cpu")
    out = [first if s == 0 else first.with_name(f"{first.name}-seed{s}") for s in seeds]
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


def main(argv: list[str] | None = None) -> None:
    from safecdt_jax.pairs import parse_pair

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", default="CG1-CG2")
    ap.add_argument("--ckpt-seeds", default="0,1,2")
    ap.add_argument("--ratios", default="0.2,1.0")
    ap.add_argument("--episodes", type=int, default=32)
    ap.add_argument("--budget", type=float, default=30.0)
    ap.add_argument("--full-episodes", action="store_true")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/cost_terms.json"))
    args = ap.parse_args(argv)
    source, target = parse_pair(args.pair)
    ratios = [float(r) for r in args.ratios.split(",")]
    ckpts = checkpoints(source, [int(s) for s in args.ckpt_seeds.split(",")])
    rows = []
    for task in (source, target):
        per_ckpt = episodes_per_term(ckpts, task, ratios, args.episodes, args.budget,
                                     not args.full_episodes, args.seed)
        for i, cr in enumerate(ratios):
            row = {"task": task, "cr": cr}
            for k in per_ckpt[0]:
                means = [float(m[k][i].mean()) for m in per_ckpt]
                row[k] = {"mean": float(np.mean(means)), "ckpt_std": float(np.std(means)),
                          "per_ckpt": means}
            rows.append(row)
        print(f"{task}: done", file=sys.stderr, flush=True)
    terms = [k for k in rows[0] if k.startswith("cost_")]
    command = "python -m experiments.cost_terms " + " ".join(sys.argv[1:] if argv is None
                                                             else argv)
    write_json(args.out, {"command": command, "machine": machine(), "pair": args.pair,
                          "checkpoints": [str(c) for c in ckpts], "episodes": args.episodes,
                          "budget": args.budget, "stop_over_budget": not args.full_episodes,
                          "rr": RR, "rows": rows})
    fmt = lambda s: f"{s['mean']:.2f} ({s['ckpt_std']:.2f})"
    body = markdown_table(
        ["task", "CR", "return", "cost", *(t.removeprefix("cost_") for t in terms)],
        [[r["task"], f"{r['cr']:g}", fmt(r["return"]), fmt(r["cost"]),
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
