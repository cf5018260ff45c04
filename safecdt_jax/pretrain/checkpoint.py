"""Orbax checkpoints of CDT pretraining: the whole `TrainState` plus a JSON record of its configs.

A checkpoint folder holds one orbax step folder per saved step (`<dir>/<step>/{state,meta}`),
each written to a temporary name and renamed when complete, so a reader never sees half of one.
`meta` is plain JSON: task and sizes, the model/optimiser/run configs, a data set summary
(including `reference_return`), the loss history, package versions and wall time.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any, NamedTuple

import jax

from safecdt_jax.model import CDTConfig, OptimConfig, Params, TrainState, init_train_state
from safecdt_jax.pretrain.config import PretrainConfig
from safecdt_jax.pretrain.normalize import IONorm, fold_io_norm

# Bump when the layout of `meta` or the state changes incompatibly. 2: every config field and
# the label support recorded (format 1's older layouts were read through defaults).
FORMAT = 2

# Fields of the run config that may differ between a checkpoint and a resumed run: how far to
# train, how often to save and how many updates one jitted call runs do not change what update
# `i` computes (its key is fold_in(seed, i)); bit-identity is tested for an unchanged chunk.
RESUMABLE_FIELDS = frozenset({"pretrain.steps", "pretrain.checkpoint_every",
                              "pretrain.max_to_keep", "pretrain.chunk"})


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, or does not fit the request (one-line message)."""


class Checkpoint(NamedTuple):
    """A loaded policy: CDT `params` (raw observation and action units), its `cfg` and the
    checkpoint's JSON `meta`."""

    params: Params
    cfg: CDTConfig
    meta: dict[str, Any]


def _quiet_orbax() -> None:
    # Orbax logs every save/restore step at INFO through absl; keep the console for the bar.
    for name in ("absl", "orbax"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _manager(path: str | os.PathLike, *, max_to_keep: int | None = None, read_only: bool = False):
    import orbax.checkpoint as ocp

    _quiet_orbax()
    local = {}
    if jax.distributed.is_initialized():
        # Among cooperating processes (`safecdt_jax.distributed`) each reads, and process 0
        # alone writes, its own copy: orbax's default would make every save and restore wait
        # for all processes, so process 0 pretraining alone would hang.
        me = jax.process_index()
        local = dict(multiprocessing_options=ocp.options.MultiprocessingOptions(
            primary_host=me, active_processes={me}))
        if not read_only:  # orbax cannot create the folder for a subset of processes
            Path(path).mkdir(parents=True, exist_ok=True)
    options = ocp.CheckpointManagerOptions(
        max_to_keep=max_to_keep,
        # Readers open with create=False rather than orbax's read_only, which warns on every use.
        create=not (read_only or local),
        # Synchronous: a save is complete (and renamed into place) when `save` returns.
        enable_async_checkpointing=False,
        **local,
    )
    return ocp.CheckpointManager(Path(path).absolute(), options=options,
                                 item_names=("state", "meta"))


def checkpoint_steps(path: str | os.PathLike) -> list[int]:
    """Steps of the complete checkpoints in folder `path`, ascending ([] if none or no folder)."""
    if not Path(path).is_dir():
        return []
    with _manager(path, read_only=True) as mngr:
        return sorted(mngr.all_steps())


def save_checkpoint(
    path: str | os.PathLike, state: TrainState, meta: dict[str, Any], max_to_keep: int = 2
) -> int:
    """Save `state` and `meta` (JSON-able) as the checkpoint of step `state.step`; returns it.

    Overwrites an existing checkpoint of the same step; keeps the newest `max_to_keep`.
    """
    import orbax.checkpoint as ocp

    step = int(state.step)
    with _manager(path, max_to_keep=max_to_keep) as mngr:
        if step in mngr.all_steps():
            mngr.delete(step)
        mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                meta=ocp.args.JsonSave(meta)))
        mngr.wait_until_finished()
    return step


def _resolve_step(path: str | os.PathLike, step: int | None) -> int:
    steps = checkpoint_steps(path)
    if not steps:
        where = "does not exist" if not Path(path).exists() else "holds no complete checkpoint"
        raise CheckpointError(f"checkpoint folder {os.fspath(path)} {where}")
    if step is None:
        return steps[-1]
    if step not in steps:
        raise CheckpointError(f"{os.fspath(path)} has no checkpoint of step {step} (has {steps})")
    return step


def read_meta(path: str | os.PathLike, step: int | None = None) -> dict[str, Any]:
    """The JSON metadata of checkpoint `step` (default: the latest) in folder `path`."""
    import orbax.checkpoint as ocp

    step = _resolve_step(path, step)
    with _manager(path, read_only=True) as mngr:
        meta = mngr.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))["meta"]
    if meta.get("format") != FORMAT:
        raise CheckpointError(
            f"{os.fspath(path)}: checkpoint format {meta.get('format')!r}, this code reads {FORMAT}"
        )
    return meta


def configs_from_meta(meta: dict[str, Any]) -> tuple[CDTConfig, OptimConfig, PretrainConfig]:
    """The model, optimiser and run configs recorded in a checkpoint's metadata."""
    model = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["model"].items()}
    pretrain = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["pretrain"].items()}
    return CDTConfig(**model), OptimConfig(**meta["optim"]), PretrainConfig(**pretrain)


def restore_state(
    path: str | os.PathLike, cdt_cfg: CDTConfig, optim: OptimConfig, step: int | None = None
) -> TrainState:
    """The full `TrainState` of checkpoint `step` (default latest), bit-exact as saved."""
    import orbax.checkpoint as ocp

    step = _resolve_step(path, step)
    # The structure (and dtypes) come from a shape-only init: nothing is computed.
    target = jax.eval_shape(lambda k: init_train_state(k, cdt_cfg, optim), jax.random.key(0))
    if jax.distributed.is_initialized():
        # Without a sharding orbax places each leaf as saved, on process 0's device, which
        # another cooperating process cannot address: restore onto this process's own.
        mine = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        target = jax.tree.map(lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=mine),
                              target)
    with _manager(path, read_only=True) as mngr:
        out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target)))
    return out["state"]


def load_checkpoint(
    path: str | os.PathLike, step: int | None = None
) -> Checkpoint:
    """Load the CDT params, config and metadata of checkpoint `step` (default: the latest).

    A run trained on normalised data (`meta["io_norm"]`) has that normalisation folded into the
    returned params, so they read raw observations and emit raw actions like any other.
    Raises CheckpointError when the folder is missing or holds no complete checkpoint.
    """
    meta = read_meta(path, step)
    cdt_cfg, optim, _ = configs_from_meta(meta)
    params = restore_state(path, cdt_cfg, optim, meta["step"]).params
    if "io_norm" in meta:
        params = fold_io_norm(params, IONorm.from_json(meta["io_norm"]))
    return Checkpoint(params, cdt_cfg, meta)


def load_policy(
    path: str | os.PathLike, task: str | None = None, obs_dim: int | None = None
) -> Checkpoint:
    """`load_checkpoint` for deployment on `task`, checking that the model fits it.

    With `task` one of `envs.NAMES`, the env's observation size, action size and horizon must
    equal the checkpoint's (so CarGoal1 -> CarGoal2 is allowed, CarGoal -> CarCircle is not); any
    other task name must equal the checkpoint's task. `obs_dim`, if given, must equal the
    checkpoint's. Raises CheckpointError (one line, naming both sides) otherwise.
    """
    ckpt = load_checkpoint(path)
    cfg, src = ckpt.cfg, ckpt.meta.get("task")
    where = f"checkpoint {os.fspath(path)} (task {src}, obs {cfg.obs_dim}, act {cfg.act_dim}, " \
            f"episode {cfg.episode_len})"
    if obs_dim is not None and obs_dim != cfg.obs_dim:
        raise CheckpointError(f"{where} does not fit observation size {obs_dim}")
    if task is not None:
        sizes = task_sizes(task)
        if sizes is None and task != src:
            raise CheckpointError(f"{where} was trained on another task than {task}")
        if sizes is not None and sizes != (cfg.obs_dim, cfg.act_dim, cfg.episode_len):
            o, a, e = sizes
            raise CheckpointError(
                f"{where} does not fit task {task} (obs {o}, act {a}, episode {e})"
            )
    return ckpt


def with_action_mode(policy: Checkpoint, stochastic_actions: bool | None) -> Checkpoint:
    """`policy` acting with samples of its Gaussian (True) or its mean (False) in rollouts;
    None keeps the checkpoint's own `CDTConfig.stochastic_actions`."""
    if stochastic_actions is None:
        return policy
    return policy._replace(cfg=policy.cfg.replace(stochastic_actions=bool(stochastic_actions)))


def task_sizes(task: str) -> tuple[int, int, int] | None:
    """(obs_dim, act_dim, episode_len) of a task in `envs.NAMES`, else None (no env built)."""
    from safecdt_jax import envs
    if task not in envs.NAMES:
        return None
    env, _ = envs.make(task)
    return env.observation_size, env.action_size, env.episode_length


def config_record(
    cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig
) -> dict[str, dict[str, Any]]:
    """The configs as `meta` stores them: `{"model": {...}, "optim": {...}, "pretrain": {...}}`."""
    plain = lambda c: {k: list(v) if isinstance(v, tuple) else v
                       for k, v in dataclasses.asdict(c).items()}
    return {"model": plain(cdt_cfg), "optim": plain(optim), "pretrain": plain(cfg)}


def config_diff(saved: dict[str, Any], requested: dict[str, Any]) -> list[str]:
    """Fields that differ between two metas, as `"section.field: saved -> requested"` strings.

    Compares the task, the three configs and the data set fingerprint; fields in
    `RESUMABLE_FIELDS` are ignored (a resumed run may train longer or save more often).
    """
    diffs = []
    for section in ("model", "optim", "pretrain"):
        a, b = saved.get(section, {}), requested.get(section, {})
        for name in sorted(set(a) | set(b)):
            field = f"{section}.{name}"
            if field not in RESUMABLE_FIELDS and a.get(name) != b.get(name):
                diffs.append(f"{field}: {a.get(name)!r} -> {b.get(name)!r}")
    if saved.get("task") != requested.get("task"):
        diffs.append(f"task: {saved.get('task')!r} -> {requested.get('task')!r}")
    fa = saved.get("dataset", {}).get("fingerprint")
    fb = requested.get("dataset", {}).get("fingerprint")
    if fa != fb:
        diffs.append(f"dataset.fingerprint: {fa} -> {fb}")
    return diffs
