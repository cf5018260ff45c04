"""`pretrain`: data file -> trained CDT checkpoint folder (fresh, resumed, or reused)."""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from safecdt_jax.data import (
    Dataset,
    costs_to_go,
    episode_costs,
    episode_returns,
    load_dataset,
    returns_to_go,
    trajectory_weights,
)
from safecdt_jax.distributed import barrier, is_writer, local_copy, spans_processes
from safecdt_jax.model import (
    CDTConfig,
    OptimConfig,
    TrainState,
    count_params,
    init_train_state,
    param_shapes,
    with_token_edges,
)
from safecdt_jax.paths import checkpoint_dir
from safecdt_jax.pretrain.checkpoint import (
    FORMAT,
    CheckpointError,
    checkpoint_steps,
    config_diff,
    config_record,
    read_meta,
    restore_state,
    save_checkpoint,
    task_sizes,
)
from safecdt_jax.pretrain.config import PretrainConfig, default_pretrain
from safecdt_jax.pretrain.loop import History, labelled, prepare_data, stream_key, train
from safecdt_jax.pretrain.normalize import IONorm, fit_io_norm, normalise_dataset
from safecdt_jax.pretrain.support import label_support
from safecdt_jax.tensorboard import write_scalars
from safecdt_jax.versions import versions


def tensorboard_dir(ckpt: str | os.PathLike) -> Path:
    """Where a checkpoint folder's pretraining curves go as TensorBoard events: beside it,
    `<folder>-tensorboard` (the checkpoint folder itself holds only orbax's steps)."""
    ckpt = Path(ckpt)
    return ckpt.parent / f"{ckpt.name}-tensorboard"


class RunSpec(NamedTuple):
    """Everything a run is determined by, before any training: inputs, configs and `meta`."""

    data: Dataset
    task: str
    out: Path
    cdt_cfg: CDTConfig
    optim: OptimConfig
    cfg: PretrainConfig
    meta: dict[str, Any]


class PretrainResult(NamedTuple):
    """What `pretrain` returns: checkpoint folder, final training state, loss history, final
    metadata. `state.params` are in the units the model trained in, normalised when the run
    scales actions or standardises observations (the `cpu` preset does both): to act, use
    `policy()`, whose params read raw observations and emit raw actions."""

    path: Path
    state: TrainState
    history: History
    meta: dict[str, Any]

    def policy(self):
        """The trained policy as deployment loads it (`checkpoint.load_checkpoint`: raw-unit
        params, the model config, the metadata)."""
        from safecdt_jax.pretrain.checkpoint import load_checkpoint

        return load_checkpoint(self.path)


def dataset_record(path: str | os.PathLike, data: Dataset) -> dict[str, Any]:
    """Summary of the training data for the checkpoint (raw, unscaled units; real episodes).

    `reference_return` is the 95th percentile of the episode returns (R_ref of docs/METHOD.md, the
    deployment's return unit); `cost_median` the median episode cost. `fingerprint` is a
    BLAKE2b digest of the episode arrays, so a re-collected file is told apart from the old one
    whatever its path or compression; `recipe` the digest of what the collector made the data
    from (`experts.collect.data_recipe`; None for data it did not collect), the same on every CPU.
    """
    from safecdt_jax.experts.collect import data_recipe

    returns, costs = episode_returns(data), episode_costs(data)
    digest = hashlib.blake2b(digest_size=16)
    for name in ("lengths", "observations", "actions", "rewards", "costs"):
        digest.update(np.ascontiguousarray(getattr(data, name)).tobytes())
    return {
        "path": str(Path(path).absolute()),
        "fingerprint": digest.hexdigest(),
        "recipe": data_recipe(data.attrs),
        "n_episodes": int(data.n_episodes),
        "n_transitions": int(np.sum(data.lengths)),
        "horizon": int(data.horizon),
        "reference_return": float(np.percentile(returns, 95)),
        "return_median": float(np.median(returns)),
        "return_max": float(returns.max()),
        "cost_median": float(np.median(costs)),
        "cost_mean": float(costs.mean()),
        "cost_max": float(costs.max()),
    }


def _episode_len(data: Dataset, task: str) -> int:
    """The task's horizon: the file's `episode_len` attribute, else the env's, else the data's."""
    for key in ("episode_len", "episode_length", "max_episode_steps"):
        if key in data.attrs:
            return int(data.attrs[key])
    sizes = task_sizes(task)
    return sizes[2] if sizes is not None else int(data.horizon)


def fit_token_edges(cdt_cfg: CDTConfig, data: Dataset, cfg: PretrainConfig) -> CDTConfig:
    """`cdt_cfg` with its token bin edges fitted to the steps pretraining samples: every valid
    step's RTG and CTG, weighted by its episode's sampling weight `max(0, cfg.c0 - C_i)` (OSRL's
    trajectory weights; Pareto-relabelled copies are not included), reaching at least
    `cfg.return_span` / `cfg.cost_span`. Unchanged when `token_bins == 0` or the edges are
    already set (a resumed or overridden run)."""
    if not cdt_cfg.token_bins or (cdt_cfg.return_edges and cdt_cfg.cost_edges):
        return cdt_cfg
    valid = data.valid_steps
    weights = np.broadcast_to(trajectory_weights(data, c0=cfg.c0)[:, None], valid.shape)
    steps = np.broadcast_to(np.arange(valid.shape[1])[None], valid.shape)
    const = cdt_cfg.constant_targets
    rtg, ctg = np.asarray(returns_to_go(data, const)), np.asarray(costs_to_go(data, const))
    return with_token_edges(cdt_cfg, rtg[valid], ctg[valid], weights[valid], steps[valid],
                            cfg.return_span, cfg.cost_span)


def plan(
    data_path: str | os.PathLike,
    out: str | os.PathLike | None = None,
    *,
    preset: str = "cpu",
    config: PretrainConfig | None = None,
    optim: OptimConfig | None = None,
    task: str | None = None,
    model_overrides: dict[str, Any] | None = None,
) -> RunSpec:
    """Load the data and fix every config of a run (nothing is trained or written).

    The task is `task`, else the file's `task` attribute, else the file name without suffix; a
    `task` that contradicts the file's attribute raises ValueError. Sizes come from the data;
    the horizon from `_episode_len`. Defaults: `default_pretrain(preset)`, `OptimConfig()`, and
    `out = paths.checkpoint_dir(task, preset)`.
    """
    data = load_dataset(data_path)
    file_task = data.attrs.get("task")
    if task is not None and file_task is not None and str(file_task) != task:
        raise ValueError(f"{os.fspath(data_path)} holds task {file_task}, not {task}")
    task = task or (str(file_task) if file_task is not None else Path(data_path).stem)
    cfg = config or default_pretrain(preset)
    optim = optim or OptimConfig()
    episode_len = _episode_len(data, task)
    if data.horizon > episode_len:
        raise ValueError(f"{os.fspath(data_path)}: episodes of {data.horizon} steps exceed the "
                         f"task horizon {episode_len}")
    cdt_cfg = CDTConfig.preset(preset, data.obs_dim, data.act_dim, episode_len,
                               **(model_overrides or {}))
    labels = labelled(data, cfg)
    cdt_cfg = fit_token_edges(cdt_cfg, labels, cfg)
    meta = {
        "format": FORMAT,
        "task": task,
        "preset": preset,
        "obs_dim": cdt_cfg.obs_dim,
        "act_dim": cdt_cfg.act_dim,
        "episode_len": cdt_cfg.episode_len,
        "n_params": count_params(param_shapes(cdt_cfg)),
        **config_record(cdt_cfg, optim, cfg),
        "dataset": dataset_record(data_path, data),
        "token_support": label_support(labels, cfg.c0),
        "versions": versions(),
    }
    if cfg.scale_actions or cfg.standardize_obs:  # a function of the data and these flags
        meta["io_norm"] = fit_io_norm(data, observations=cfg.standardize_obs,
                                      actions=cfg.scale_actions).to_json()
    out = Path(out) if out is not None else checkpoint_dir(task, preset)
    return RunSpec(data, task, out, cdt_cfg, optim, cfg, meta)


def pretrain(
    data_path: str | os.PathLike,
    out: str | os.PathLike | None = None,
    *,
    preset: str = "cpu",
    config: PretrainConfig | None = None,
    optim: OptimConfig | None = None,
    task: str | None = None,
    model_overrides: dict[str, Any] | None = None,
    resume: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    devices: list | None = None,
) -> PretrainResult:
    """Pretrain a CDT preset on a DSRL-format file, checkpointing into folder `out`.

    See `plan` for how the task, sizes and defaults are chosen, and `train_run` for `resume`,
    `overwrite` and `devices` (data-parallel). Returns `PretrainResult(path, state, history,
    meta)`.
    """
    spec = plan(data_path, out, preset=preset, config=config, optim=optim, task=task,
                model_overrides=model_overrides)
    return train_run(spec, resume=resume, overwrite=overwrite, progress=progress,
                     devices=devices)


def train_run(
    spec: RunSpec, *, resume: bool = False, overwrite: bool = False, progress: bool = True,
    devices: list | None = None,
) -> PretrainResult:
    """Train the run `spec` (from `plan`), checkpointing into `spec.out`.

    With `scale_actions` or `standardize_obs` the state trains on normalised data
    (`pretrain.normalize`); its params are in those units, and `load_checkpoint` folds them back
    to raw ones.

    With `resume`, training continues from the latest checkpoint in the folder (if any) up to
    `spec.cfg.steps` total updates, bit-identical to an uninterrupted run; a checkpoint whose
    configs or data differ raises CheckpointError naming the fields. Without `resume`, a folder
    that already holds checkpoints raises CheckpointError unless `overwrite` (which deletes them
    first). Checkpoints are written every `checkpoint_every` updates and at the end.
    `devices` (several): train data-parallel over them (`loop.train`), the same up to float
    summation order; with several cooperating processes every process trains its share of
    each batch and process 0 alone writes the checkpoints.
    Returns `PretrainResult(path, state, history, meta)`; `meta` is the last saved metadata.
    """
    out, cfg = spec.out, spec.cfg
    # Training together with other processes (devices of several): process 0 writes, and they
    # meet at barriers. Otherwise (alone, or process 0 preparing alone) this process writes.
    together = devices is not None and spans_processes(devices)
    writer = is_writer() or not together
    existing = checkpoint_steps(out)
    if existing and overwrite:
        if writer:
            shutil.rmtree(out)
        if together:
            barrier("pretrain:overwrite")  # no process reads the folder while it is deleted
        existing = []
    if existing and not resume:
        raise CheckpointError(f"{out} already holds a checkpoint (step {existing[-1]}); "
                              "resume it or choose overwrite / another folder")
    history = History.empty()
    if existing:
        saved = read_meta(out)
        diffs = config_diff(saved, spec.meta)
        if diffs:
            raise CheckpointError(f"cannot resume {out}: its run differs in " + "; ".join(diffs))
        state = restore_state(out, spec.cdt_cfg, spec.optim)
        history = History.from_json(saved.get("history", {}))
    else:
        state = init_train_state(stream_key(cfg.seed, "init"), spec.cdt_cfg, spec.optim)
        shutil.rmtree(tensorboard_dir(out), ignore_errors=True)  # curves of a deleted run

    t0 = time.perf_counter()
    data = spec.data
    if "io_norm" in spec.meta:
        data = normalise_dataset(data, IONorm.from_json(spec.meta["io_norm"]))
    data, weights, n_relabelled = prepare_data(data, cfg)
    dataset = {**spec.meta["dataset"], "n_relabelled": n_relabelled,
               "n_sampled": int(np.sum(np.asarray(weights) > 0))}
    setup_s = time.perf_counter() - t0
    last = {"step": int(state.step), "meta": None,  # the newest checkpoint written by this call
            "curves": len(history.step)}  # history points already in the TensorBoard events

    def save(state: TrainState, history: History) -> None:
        record = save_run(spec, local_copy(state) if writer else None, history, dataset,
                          setup_s, last["curves"])
        last.update(step=int(state.step), meta=record, curves=len(history.step))

    def on_chunk(state: TrainState, history: History) -> None:
        # Save when this chunk crossed a multiple of checkpoint_every (the end is saved below).
        step, every = int(state.step), cfg.checkpoint_every
        if every and step < cfg.steps and step // every > last["step"] // every:
            save(state, history)

    state, history = train(state, data, weights, spec.cdt_cfg, spec.optim, cfg,
                           history=history, on_chunk=on_chunk,
                           progress=progress and writer, devices=devices)
    if int(state.step) != last["step"]:  # trained since the last save (always, unless resumed
        save(state, history)               # a run that had already reached its steps)
    if together:
        barrier("pretrain:saved")  # the checkpoint is complete before any process reads it
    meta = last["meta"] if last["meta"] is not None else read_meta(out)
    return PretrainResult(out, state, history, meta)


def save_run(spec: RunSpec, state: TrainState | None, history: History,
             dataset: dict[str, Any], setup_s: float, curves_from: int) -> dict[str, Any]:
    """Writes `state` as the checkpoint of its step in `spec.out`, with the run's metadata, and
    the history points from index `curves_from` on as TensorBoard events; returns the
    metadata. `state` None (a process that does not write): only the metadata."""
    step = int(history.step[-1]) if state is None else int(state.step)
    record = {**spec.meta, "dataset": dataset, "step": step,
              "finished": step >= spec.cfg.steps, "history": history.to_json(),
              "wall_time_s": history.wall_s, "setup_s": setup_s,
              "saved_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    if state is not None:
        save_checkpoint(spec.out, state, record, max_to_keep=spec.cfg.max_to_keep)
        curves = {f"pretrain/{k}": v for k, v in history.metrics.items()}
        write_scalars(tensorboard_dir(spec.out), curves, history.step, start=curves_from)
    return record


def ensure_checkpoint(
    data_path: str | os.PathLike,
    task: str | None,
    preset: str = "cpu",
    steps: int | None = None,
    *,
    batch_size: int | None = None,
    seed: int = 0,
    out: str | os.PathLike | None = None,
    optim: OptimConfig | None = None,
    overwrite: bool = False,
    progress: bool = True,
    model_overrides: dict[str, Any] | None = None,
    pretrain_overrides: dict[str, Any] | None = None,
) -> Path:
    """The folder of a pretrained checkpoint for this data and config, training only if needed.

    `model_overrides` replace fields of the preset's `CDTConfig` (e.g. `token_bins`),
    `pretrain_overrides` fields of its `PretrainConfig` (e.g. `labels`). `task` None: the
    file's `task` attribute, else its name (`plan`).

    Reuses the checkpoint in `out` (default `paths.checkpoint_dir(task, preset)`) when its
    configs and data match and it has reached `steps` (default: the preset's); resumes it when
    it matches but is shorter; trains from scratch when the folder is empty. A checkpoint with
    another config raises CheckpointError naming the fields, unless `overwrite` (retrain).
    """
    overrides: dict[str, Any] = {"seed": seed, **(pretrain_overrides or {})}
    if steps is not None:
        overrides["steps"] = steps
    if batch_size is not None:
        overrides["batch_size"] = batch_size
    cfg = default_pretrain(preset, **overrides)
    spec = plan(data_path, out, preset=preset, config=cfg, optim=optim, task=task,
                model_overrides=model_overrides)
    done = checkpoint_steps(spec.out)
    retrain = False
    if done:
        try:
            diffs = config_diff(read_meta(spec.out), spec.meta)
        except CheckpointError as e:  # written by an older format: unreadable, so retrain
            if not overwrite:
                raise
            diffs = [str(e)]
        if diffs and not overwrite:
            raise CheckpointError(f"{spec.out} holds a checkpoint of another run ("
                                  + "; ".join(diffs) + "); pass overwrite to retrain")
        retrain = bool(diffs)
        if not retrain and done[-1] >= cfg.steps:
            return spec.out
    train_run(spec, resume=True, overwrite=retrain, progress=progress)
    return spec.out
