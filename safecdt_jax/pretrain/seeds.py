"""Several pretraining seeds in one compiled program: the chunk `vmap`ped over seeds.

A seed decides three things of a run: the initial parameters, the Pareto-relabelled copies
(which episodes are copied, with which targets) and every update's windows and dropout. The
step arrays (observations, actions, rewards, costs) are the same for all seeds, so they are
held once; each seed gets its own episode list as a view (`SeedData.source`: the row each of
its episodes reads), its lengths, label offsets and sampling weights, padded with empty
episodes to a common count (in practice every seed gets as many copies: their number depends
on the grid filter's cell counts, not on the draw). Every seed draws the windows its single
run draws (`sample_windows`' inverse-CDF draw ignores trailing zero weights, but for a uniform
draw that rounds onto the very top of the CDF, about 2^-24 per window), so a vmapped run
equals the single runs up to the batched matmuls' float summation order.

    results = pretrain_seeds("CarGoal1.hdf5", [0, 1, 2], preset="cpu")   # 3 checkpoints
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.data import Dataset, RelabelConfig, relabel_pareto, trajectory_weights
from safecdt_jax.model import CDTConfig, OptimConfig, init_train_state
from safecdt_jax.pretrain.checkpoint import (
    CheckpointError,
    checkpoint_steps,
    config_diff,
    config_record,
    read_meta,
    restore_state,
)
from safecdt_jax.pretrain.config import PretrainConfig, default_pretrain
from safecdt_jax.pretrain.loop import (
    METRICS,
    History,
    chunk_body,
    labelled,
    program_config,
    run_key,
    stream_key,
)
from safecdt_jax.pretrain.normalize import IONorm, normalise_dataset
from safecdt_jax.pretrain.run import PretrainResult, RunSpec, plan, save_run, tensorboard_dir


class SeedData(NamedTuple):
    """The sampler's arrays for S seeds: step arrays shared ([n, T, ...]), episode lists per
    seed ([S, N]: `source` row, length and label offsets; padding has length 0)."""

    observations: jax.Array
    actions: jax.Array
    rewards: jax.Array
    costs: jax.Array
    lengths: jax.Array
    return_offset: jax.Array
    cost_offset: jax.Array
    source: jax.Array


# vmap axes of `SeedData`: shared step arrays, per-seed episode lists.
_SEED_AXES = SeedData(None, None, None, None, 0, 0, 0, 0)


def prepare_seeds(data: Dataset, cfg: PretrainConfig,
                  seeds: Sequence[int]) -> tuple[SeedData, jax.Array, list[int]]:
    """`prepare_data` for every seed of `seeds` at once: `(seed_data, weights [S, N],
    n_relabelled per seed)`. Seed k's episode list is the labelled data followed by its own
    relabelled copies (drawn from `stream_key(k, "relabel")`, as a single run draws them)."""
    base = labelled(data, cfg)
    n = base.n_episodes
    lists = []
    for seed in seeds:
        run = base
        if cfg.relabel:
            run = relabel_pareto(stream_key(seed, "relabel"), base,
                                 RelabelConfig(percent=cfg.relabel_percent))
        copied = np.asarray(run.episode_info.get("relabel_source", np.full(n, -1)))
        source = np.where(np.arange(run.n_episodes) < n, np.arange(run.n_episodes), copied)
        lists.append((source, np.asarray(run.lengths), np.asarray(run.return_offset),
                      np.asarray(run.cost_offset), np.asarray(trajectory_weights(run, c0=cfg.c0))))
    width = max(len(x[0]) for x in lists)
    pad = lambda x: np.pad(x, (0, width - len(x)))  # zeros: row 0, length 0, weight 0
    source, lengths, r_off, c_off, weights = (np.stack([pad(x[i]) for x in lists])
                                              for i in range(5))
    arrays = SeedData(np.asarray(base.observations), np.asarray(base.actions),
                      np.asarray(base.rewards), np.asarray(base.costs),
                      lengths.astype(np.asarray(base.lengths).dtype),
                      r_off.astype(np.float32), c_off.astype(np.float32),
                      source.astype(np.int32))
    return (jax.device_put(arrays), jax.device_put(weights.astype(np.float32)),
            [len(x[0]) - n for x in lists])


def make_seeds_chunk(cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig):
    """Jitted `train_chunk(states, keys, seed_data, weights, stop) -> (states, metrics)`: the
    single run's chunk (`loop.chunk_body`) vmapped over seeds (states, keys, episode lists and
    weights with a leading [S] axis; metrics [S]). The states are donated. Cached on the fields
    that shape the program (`loop.program_config`), as the single run's chunk is."""
    return _seeds_chunk(cdt_cfg, optim, program_config(cfg))


@functools.lru_cache(maxsize=4)
def _seeds_chunk(cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig):
    body = chunk_body(cdt_cfg, optim, cfg)
    return jax.jit(jax.vmap(body, in_axes=(0, 0, _SEED_AXES, 0, None)), donate_argnums=0)


def _specs(data_path, seeds: Sequence[int], outs, preset: str, config: PretrainConfig | None,
           optim: OptimConfig | None, task: str | None,
           model_overrides: dict[str, Any] | None) -> list[RunSpec]:
    """One `RunSpec` per seed, each what `plan` gives for that seed and folder (the data are
    loaded and the token edges fitted once: neither depends on the seed)."""
    cfg = config or default_pretrain(preset)
    first = plan(data_path, outs[0], preset=preset, config=cfg.replace(seed=int(seeds[0])),
                 optim=optim, task=task, model_overrides=model_overrides)
    specs = []
    for seed, out in zip(seeds, outs, strict=True):
        run_cfg = cfg.replace(seed=int(seed))
        meta = first.meta | config_record(first.cdt_cfg, first.optim, run_cfg)
        specs.append(first._replace(out=Path(out), cfg=run_cfg, meta=meta))
    return specs


def default_outs(task: str, preset: str, seeds: Sequence[int]) -> list[Path]:
    """Checkpoint folders of a seed sweep: `$SAFECDT_CACHE/checkpoints/TASK-PRESET-seedK`."""
    from safecdt_jax.paths import checkpoint_dir

    root = checkpoint_dir(task, preset)
    return [root.parent / f"{root.name}-seed{int(k)}" for k in seeds]


def pretrain_seeds(
    data_path: str | os.PathLike,
    seeds: Sequence[int],
    outs: Sequence[str | os.PathLike] | None = None,
    *,
    preset: str = "cpu",
    config: PretrainConfig | None = None,
    optim: OptimConfig | None = None,
    task: str | None = None,
    model_overrides: dict[str, Any] | None = None,
    progress: bool = True,
    overwrite: bool = False,
) -> list[PretrainResult]:
    """Pretrains one CDT per seed of `seeds` on one data file, all in one compiled program,
    each checkpointed into its own folder (`outs`, default `default_outs`) exactly as
    `pretrain(..., config=config.replace(seed=k))` would write it (same metadata, so `deploy`,
    `evaluate` and `ensure_checkpoint` read them as single runs).

    Resumable: a folder that holds a checkpoint of the same run continues from its step (the
    seeds may stand at different steps; finished ones idle; nothing is compiled when all are
    finished), one of another run (or an older format) raises CheckpointError naming the
    fields, unless `overwrite`: then it is deleted and that seed trains afresh. Returns a
    `PretrainResult` per seed.
    """
    import shutil

    from tqdm import tqdm

    seeds = [int(k) for k in seeds]
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"pretrain_seeds: give distinct seeds, got {seeds}")
    if outs is None:  # the task as `plan` names it, from the file's attributes alone
        from safecdt_jax.data.collect import file_attrs

        name = task or (file_attrs(data_path) or {}).get("task") or Path(data_path).stem
        outs = default_outs(str(name), preset, seeds)
    outs = list(outs)
    specs = _specs(data_path, seeds, outs, preset, config, optim, task, model_overrides)
    first = specs[0]
    states, histories = [], []
    for spec in specs:
        if checkpoint_steps(spec.out):
            try:
                diffs = config_diff(read_meta(spec.out), spec.meta)
            except CheckpointError as e:  # an older format
                diffs = [str(e)]
            if diffs and not overwrite:
                raise CheckpointError(f"cannot resume {spec.out}: its run differs in "
                                      + "; ".join(diffs))
            if diffs:
                shutil.rmtree(spec.out)
        if checkpoint_steps(spec.out):
            states.append(restore_state(spec.out, spec.cdt_cfg, spec.optim))
            histories.append(History.from_json(read_meta(spec.out).get("history", {})))
        else:
            states.append(init_train_state(stream_key(spec.cfg.seed, "init"), spec.cdt_cfg,
                                           spec.optim))
            histories.append(History.empty())
            shutil.rmtree(tensorboard_dir(spec.out), ignore_errors=True)  # old curves
    if all(int(st.step) >= spec.cfg.steps for st, spec in zip(states, specs, strict=True)):
        return [PretrainResult(spec.out, st, h, read_meta(spec.out))
                for spec, st, h in zip(specs, states, histories, strict=True)]
    t0 = time.perf_counter()
    data = first.data
    if "io_norm" in first.meta:
        data = normalise_dataset(data, IONorm.from_json(first.meta["io_norm"]))
    arrays, weights, n_relabelled = prepare_seeds(data, first.cfg, seeds)
    setup_s = time.perf_counter() - t0
    records = [{**spec.meta["dataset"], "n_relabelled": m,
                "n_sampled": int(np.sum(np.asarray(w) > 0))}
               for spec, m, w in zip(specs, n_relabelled, weights, strict=True)]
    state = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    keys = jnp.stack([run_key(k) for k in seeds])
    total = first.cfg.steps
    stop = jnp.asarray(total, jnp.int32)
    chunk_fn = make_seeds_chunk(first.cdt_cfg, first.optim, first.cfg)
    curves_from = [len(h.step) for h in histories]
    saved = [int(s.step) for s in states]
    every = first.cfg.checkpoint_every
    steps = np.asarray([int(s.step) for s in states])
    bar = tqdm(total=total * len(seeds), initial=int(steps.sum()), unit="step",
               disable=not progress, desc=f"pretrain x{len(seeds)}", dynamic_ncols=True)

    def save(i: int) -> dict[str, Any]:
        one = jax.tree.map(lambda x: x[i], state)
        record = save_run(specs[i], one, histories[i], records[i], setup_s, curves_from[i])
        curves_from[i], saved[i] = len(histories[i].step), int(steps[i])
        return record

    metas: list[dict[str, Any] | None] = [None] * len(seeds)
    try:
        while np.any(steps < total):
            t = time.perf_counter()
            state, metrics = chunk_fn(state, keys, arrays, weights, stop)
            metrics = jax.device_get(metrics)
            wall = time.perf_counter() - t
            done = np.asarray(metrics.pop("updates"))
            for i in np.flatnonzero(done):  # seeds that trained in this chunk
                steps[i] += done[i]
                h = histories[i]
                h.step.append(int(steps[i]))
                for k in METRICS:
                    h.metrics[k].append(float(metrics[k][i]))
                histories[i] = h._replace(wall_s=h.wall_s + wall)
                if every and steps[i] < total and steps[i] // every > saved[i] // every:
                    metas[i] = save(i)
            bar.update(int(done.sum()))
            bar.set_postfix(ll=" ".join(f"{x:.2f}" for x in metrics["log_likelihood"]))
    finally:
        bar.close()
    results = []
    for i, spec in enumerate(specs):
        if saved[i] != steps[i] or (metas[i] is None and not checkpoint_steps(spec.out)):
            metas[i] = save(i)
        meta = metas[i] if metas[i] is not None else read_meta(spec.out)
        results.append(PretrainResult(spec.out, jax.tree.map(lambda x, i=i: x[i], state),
                                      histories[i], meta))
    return results


__all__ = ["SeedData", "default_outs", "make_seeds_chunk", "prepare_seeds", "pretrain_seeds"]
