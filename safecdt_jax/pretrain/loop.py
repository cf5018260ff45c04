"""The pretraining loop: `chunk` updates per jitted `lax.scan`, batches sampled on the device.

The data set is put on the device once; every update draws its windows there with
`sample_windows`, so the host only touches the state between chunks (progress bar, checkpoints).
The key of update `i` is `fold_in(run_key, i)`: the result depends on the seed and the update
index only, never on how the steps were split into chunks or calls, so resuming is bit-exact.

Data parallel (`train(..., devices=...)`): over several devices, of one process or of several
cooperating ones (`safecdt_jax.distributed`), each update's batch of windows is sharded over a
`('data',)` mesh while the state and the data set are replicated; the compiler partitions the
forward and backward passes and reduces the gradient across devices. The same windows are
drawn as on one device, so the result equals one device's up to float summation order.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from safecdt_jax.data import (
    Dataset,
    RelabelConfig,
    policy_mean_labels,
    relabel_pareto,
    sample_windows,
    trajectory_weights,
)
from safecdt_jax.model import CDTConfig, OptimConfig, TrainState, make_train_step
from safecdt_jax.pretrain.config import PretrainConfig

# Per-update metrics averaged over a chunk (names from `cdt_loss`'s aux and the train step).
METRICS = ("loss", "act_loss", "cost_loss", "cost_accuracy", "log_likelihood", "entropy",
           "temperature")


class TrainData(NamedTuple):
    """The episode arrays `sample_windows` reads, as device arrays (padded `[n, T, ...]`)."""

    observations: jax.Array
    actions: jax.Array
    rewards: jax.Array
    costs: jax.Array
    lengths: jax.Array
    return_offset: jax.Array
    cost_offset: jax.Array


def labelled(data: Dataset, cfg: PretrainConfig) -> Dataset:
    """The data with the return/cost labels `cfg.labels` asks for (before any relabelling)."""
    policy = cfg.labels == "policy" or (cfg.labels == "auto" and "snapshot" in data.episode_info)
    return policy_mean_labels(data) if policy else data


def prepare_data(data: Dataset, cfg: PretrainConfig) -> tuple[TrainData, jax.Array, int]:
    """Relabel (if `cfg.relabel`), weight and move a data set to the device, once.

    Returns `(train_data, weights, n_relabelled)`: the arrays the sampler needs (next
    observations, flags and episode info stay on the host), the OSRL trajectory weights
    `max(0, c0 - C_i)` normalised over all episodes, and how many relabelled copies were added.
    Relabelling draws from a key of its own (`stream_key(seed, "relabel")`), so it is the same on
    every (re)start of the run.
    """
    n_real = data.n_episodes
    data = labelled(data, cfg)
    if cfg.relabel:
        data = relabel_pareto(stream_key(cfg.seed, "relabel"), data,
                              RelabelConfig(percent=cfg.relabel_percent))
    weights = trajectory_weights(data, c0=cfg.c0)
    arrays = TrainData(*(np.asarray(getattr(data, f)) for f in TrainData._fields))
    return jax.device_put(arrays), jax.device_put(weights), data.n_episodes - n_real


def run_key(seed: int) -> jax.Array:
    """The run's root PRNG key; update `i` uses `fold_in(run_key(seed), i)`."""
    return jax.random.key(seed)


# Streams that are not updates fold in indices no update reaches (updates use 0 .. steps-1).
_STREAMS = {"init": 2**31 - 1, "relabel": 2**31 - 2}


def stream_key(seed: int, name: str) -> jax.Array:
    """The key of a one-off random stream of the run: `"init"` (parameters) or `"relabel"`."""
    return jax.random.fold_in(run_key(seed), _STREAMS[name])


def make_update(
    cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig,
    batch_sharding: jax.sharding.Sharding | None = None,
) -> Callable[[TrainState, jax.Array, TrainData, jax.Array], tuple[TrainState, dict]]:
    """One pretraining update `(state, key, data, weights) -> (state, aux)` (pure, not jitted).

    Draws `cfg.batch_size` windows of `cdt_cfg.seq_len` steps with update key
    `fold_in(key, state.step)`, then takes `make_train_step`'s AdamW + temperature step (its
    gradient in passes of `cfg.micro_batch` windows when that is set). With `batch_sharding`
    the windows are laid out by it (their leading, batch axis split over devices).
    """
    train_step = make_train_step(cdt_cfg, optim, cfg.micro_batch)

    def update(state: TrainState, key: jax.Array, data: TrainData, weights: jax.Array):
        k_batch, k_dropout = jax.random.split(jax.random.fold_in(key, state.step))
        windows = sample_windows(
            k_batch, data, cfg.batch_size, cdt_cfg.seq_len, weights,
            reward_scale=cdt_cfg.reward_scale, cost_scale=cdt_cfg.cost_scale,
            constant=cdt_cfg.constant_targets,
        )
        if batch_sharding is not None:
            windows = jax.lax.with_sharding_constraint(windows, batch_sharding)
        return train_step(state, windows._asdict(), k_dropout)

    return update


def make_train_chunk(
    cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig, donate: bool = False,
    mesh: jax.sharding.Mesh | None = None,
) -> Callable[..., tuple[TrainState, dict]]:
    """Jitted `train_chunk(state, key, data, weights, stop) -> (state, metrics)`.

    One `lax.scan` over `cfg.chunk` updates (`make_update`, update `i` keyed by
    `fold_in(key, i)`); updates whose `state.step` has reached `stop` (int, traced) are skipped,
    so a run of any length uses one compiled program. `metrics` holds the mean of each `METRICS`
    entry over the updates done (0 if none) and `updates`, their number.
    `donate=True` lets XLA reuse the input state's buffers (the caller must not reuse it).
    Cached: only the fields that shape the program (batch size, chunk, scales) key the cache,
    so runs differing in seed or length share one compile.
    With a `('data',)` `mesh` (several devices) every input and output is replicated over it
    and each update's batch sharded along it (`make_update`); `cfg.batch_size` must be a
    multiple of its size.
    """
    if mesh is not None and cfg.batch_size % mesh.size:
        raise ValueError(f"data-parallel pretraining needs the batch size ({cfg.batch_size}) to "
                         f"be a multiple of the device count ({mesh.size})")
    return _train_chunk(cdt_cfg, optim, program_config(cfg), donate, mesh)


def chunk_body(cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig,
               batch_sharding: jax.sharding.Sharding | None = None) -> Callable:
    """The pure (unjitted) `train_chunk(state, key, data, weights, stop) -> (state, metrics)`
    of `make_train_chunk`: `cfg.chunk` updates in one `lax.scan`, those at `stop` skipped."""
    update = make_update(cdt_cfg, optim, cfg, batch_sharding)

    def train_chunk(state, key, data, weights, stop):
        aux_shape = jax.eval_shape(update, state, key, data, weights)[1]
        idle = {k: jnp.zeros(s.shape, s.dtype) for k, s in aux_shape.items()}

        def body(state, _):
            active = state.step < stop
            # cond, not where: a skipped update costs nothing in one run (vmapped over seeds
            # it becomes a select: a seed that has finished, or resumed further than the
            # others, still computes its updates, and they are dropped).
            state, aux = jax.lax.cond(
                active, lambda s: update(s, key, data, weights), lambda s: (s, idle), state
            )
            return state, ({k: aux[k] for k in METRICS}, active)

        state, (aux, active) = jax.lax.scan(body, state, None, length=cfg.chunk)
        done = active.sum()
        weight = active.astype(jnp.float32) / jnp.maximum(done, 1)
        metrics = {k: (v * weight).sum() for k, v in aux.items()}
        return state, {**metrics, "updates": done}

    return train_chunk


def program_config(cfg: PretrainConfig) -> PretrainConfig:
    """`cfg` with every field that does not shape the compiled chunk set to a fixed value, so
    runs differing only in seed, length or labels share one compile."""
    return cfg.replace(steps=1, seed=0, c0=1.0, relabel=False, relabel_percent=0.2,
                       labels="episode", checkpoint_every=0, max_to_keep=1)


@functools.lru_cache(maxsize=8)
def _train_chunk(cdt_cfg: CDTConfig, optim: OptimConfig, cfg: PretrainConfig, donate: bool,
                 mesh: jax.sharding.Mesh | None = None):
    batch = None if mesh is None else NamedSharding(mesh, PartitionSpec("data"))
    train_chunk = chunk_body(cdt_cfg, optim, cfg, batch)
    donate_argnums = (0,) if donate else ()
    if mesh is None:
        return jax.jit(train_chunk, donate_argnums=donate_argnums)
    # Replicated in and out: the compiler all-reduces the gradient of the sharded batch, and
    # every device (every process) ends each chunk with the same state.
    replicated = NamedSharding(mesh, PartitionSpec())
    return jax.jit(train_chunk, donate_argnums=donate_argnums, in_shardings=replicated,
                   out_shardings=replicated)


class History(NamedTuple):
    """Per-chunk training curve: `step` (updates done at the chunk's end) and metric means."""

    step: list[int]
    metrics: dict[str, list[float]]
    wall_s: float

    @staticmethod
    def empty() -> History:
        """A history with no chunks."""
        return History([], {k: [] for k in METRICS}, 0.0)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON: `{"step": [...], "wall_s": s, <metric>: [...]}`."""
        return {"step": list(self.step), "wall_s": self.wall_s, **self.metrics}

    @staticmethod
    def from_json(d: dict[str, Any]) -> History:
        """Inverse of `to_json` (metrics missing from `d` start empty)."""
        return History(list(d.get("step", [])), {k: list(d.get(k, [])) for k in METRICS},
                       float(d.get("wall_s", 0.0)))


def train(
    state: TrainState,
    data: TrainData,
    weights: jax.Array,
    cdt_cfg: CDTConfig,
    optim: OptimConfig,
    cfg: PretrainConfig,
    *,
    history: History | None = None,
    on_chunk: Callable[[TrainState, History], None] | None = None,
    progress: bool = True,
    devices: list | None = None,
) -> tuple[TrainState, History]:
    """Run updates from `state.step` up to `cfg.steps`, chunk by chunk.

    Args:
        state: start state (fresh or restored); its step says where the run is.
        data, weights: from `prepare_data`.
        cdt_cfg, optim, cfg: model, optimiser and run settings.
        history: the curve so far (resumed runs extend it).
        on_chunk: called after every chunk with the new state and history (checkpointing).
        progress: show a tqdm bar over updates: updates/s, the chunk's mean loss and action
            log-likelihood (nats per action dimension).
        devices: train data-parallel over these devices (e.g. `jax.devices()`: all of them,
            every cooperating process's); None or one device: the single-device program. The
            batch size must be a multiple of their number.

    Returns the final state (replicated over `devices`, when several) and the history (wall
    seconds summed over calls).
    """
    from tqdm import tqdm

    from safecdt_jax import distributed

    mesh = None
    if devices is not None and len(devices) > 1:
        mesh = Mesh(np.asarray(devices), ("data",))
    chunk_fn = make_train_chunk(cdt_cfg, optim, cfg, donate=True, mesh=mesh)
    history = history or History.empty()
    key, stop = run_key(cfg.seed), jnp.asarray(cfg.steps, jnp.int32)
    step = int(state.step)
    if mesh is None:
        # The donated input must not be the caller's object: copy once, then chain outputs.
        state = jax.tree.map(jnp.copy, state)
    else:  # fresh replicated copies (on every process's devices when several cooperate)
        replicated = NamedSharding(mesh, PartitionSpec())
        put = (distributed.to_global if distributed.spans_processes(devices)
               else jax.device_put)
        state, data, weights, key, stop = put((state, data, weights, key, stop), replicated)
    wall = history.wall_s
    bar = tqdm(total=cfg.steps, initial=step, unit="step", disable=not progress,
               desc="pretrain", dynamic_ncols=True)
    try:
        while step < cfg.steps:
            t = time.perf_counter()
            state, metrics = chunk_fn(state, key, data, weights, stop)
            metrics = jax.device_get(metrics)  # waits for the chunk
            wall += time.perf_counter() - t
            done = int(metrics.pop("updates"))
            step += done
            history.step.append(step)
            for k in METRICS:
                history.metrics[k].append(float(metrics[k]))
            history = history._replace(wall_s=wall)
            bar.update(done)
            # The loss mixes in T * entropy with a rising T; the log-likelihood shows the fit.
            bar.set_postfix(loss=f"{metrics['loss']:.3f}", ll=f"{metrics['log_likelihood']:.2f}")
            if on_chunk is not None:
                on_chunk(state, history)
    finally:
        bar.close()
    return state, history
