"""OSRL's CDT optimisers (AdamW with warmup + clipping, Adam on the log-temperature), one step."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from safecdt_jax.model.cdt import Params, init_cdt
from safecdt_jax.model.config import CDTConfig
from safecdt_jax.model.loss import cdt_loss, loss_normalisers, temperature_loss


@dataclass(frozen=True)
class OptimConfig:
    """Optimiser settings of CDT pretraining (defaults = OSRL's `train_cdt.py`).

    Attributes:
        learning_rate: peak AdamW learning rate.
        warmup_steps: the lr multiplier is `min((step + 1) / warmup_steps, 1)`, then constant.
        b1, b2, eps: Adam moments and epsilon (PyTorch defaults).
        weight_decay: decoupled weight decay, applied to every parameter (no exclusion groups).
        grad_clip_norm: global L2 norm the gradients are clipped to before AdamW.
        temperature_lr: learning rate of the separate Adam on the log-temperature.
        init_temperature: the entropy temperature T at the start (log T is optimised).
    """

    learning_rate: float = 1e-4
    warmup_steps: int = 500
    b1: float = 0.9
    b2: float = 0.999
    eps: float = 1e-8
    weight_decay: float = 1e-4
    grad_clip_norm: float = 0.25
    temperature_lr: float = 1e-4
    init_temperature: float = 0.1

    def __post_init__(self) -> None:
        if self.warmup_steps < 1:
            raise ValueError(f"OptimConfig.warmup_steps must be >= 1, got {self.warmup_steps}")
        for name in ("learning_rate", "grad_clip_norm", "temperature_lr", "init_temperature"):
            if not getattr(self, name) > 0:
                raise ValueError(f"OptimConfig.{name} must be positive, got {getattr(self, name)}")


class Optimizers(NamedTuple):
    """The model optimiser and the log-temperature optimiser."""

    model: optax.GradientTransformation
    temperature: optax.GradientTransformation


def learning_rate_schedule(cfg: OptimConfig) -> optax.Schedule:
    """Learning rate at optimiser step `step` (0-based): `lr * min((step + 1) / warmup, 1)`."""

    def schedule(step: jax.Array) -> jax.Array:
        # optax counts from 0, so step + 1 reproduces OSRL's LambdaLR multiplier exactly.
        return cfg.learning_rate * jnp.minimum((step + 1) / cfg.warmup_steps, 1.0)

    return schedule


def make_optimizer(cfg: OptimConfig | None = None) -> Optimizers:
    """`clip_by_global_norm -> adamw(warmup schedule)` for the model, `adam` for log T."""
    cfg = cfg or OptimConfig()
    model = optax.chain(
        optax.clip_by_global_norm(cfg.grad_clip_norm),
        optax.adamw(
            learning_rate_schedule(cfg),
            b1=cfg.b1, b2=cfg.b2, eps=cfg.eps, weight_decay=cfg.weight_decay,
        ),
    )
    temperature = optax.adam(cfg.temperature_lr, b1=cfg.b1, b2=cfg.b2, eps=cfg.eps)
    return Optimizers(model, temperature)


class TrainState(NamedTuple):
    """Everything CDT pretraining carries between steps (a pytree)."""

    params: Params
    opt_state: Any
    log_temperature: jax.Array
    temperature_opt_state: Any
    step: jax.Array


def init_train_state(
    key: jax.Array, cfg: CDTConfig, optim: OptimConfig | None = None
) -> TrainState:
    """Fresh params, optimiser states and `log_temperature = log(init_temperature)`."""
    optim = optim or OptimConfig()
    txs = make_optimizer(optim)
    params = init_cdt(key, cfg)
    log_t = jnp.asarray(math.log(optim.init_temperature), jnp.float32)
    return TrainState(
        params, txs.model.init(params), log_t, txs.temperature.init(log_t), jnp.zeros((), jnp.int32)
    )


def micro_batches(size: int, micro_batch: int) -> int:
    """How many equal passes a batch of `size` windows is split into: the fewest whose passes
    hold at most `micro_batch` windows each (0: one pass)."""
    if micro_batch < 0:
        raise ValueError(f"micro_batch must be >= 0, got {micro_batch}")
    if micro_batch == 0 or size <= micro_batch:
        return 1
    return next(n for n in range(-(-size // micro_batch), size + 1) if size % n == 0)


def batch_gradients(
    params: Params,
    log_temperature: jax.Array,
    cfg: CDTConfig,
    batch: Mapping[str, jax.Array],
    key: jax.Array | None,
    micro_batch: int = 0,
) -> tuple[tuple[jax.Array, dict[str, jax.Array]], Params]:
    """`((loss, aux), grads)` of `cdt_loss` over `batch`, in passes of at most `micro_batch`.

    A batch no larger than `micro_batch` (or `micro_batch` 0) is one `value_and_grad` pass.
    A larger one is split into `micro_batches` equal slices; a `lax.scan` runs one pass per
    slice, each divided by the whole batch's `loss_normalisers`, and sums them: the same loss,
    aux and gradient up to float summation order, with the activations of only one slice alive
    at a time (faster where a whole batch's activations spill the caches:
    docs/PERFORMANCE.md). Slice `i` draws its dropout with `fold_in(key, i)`, so the dropout
    bits differ from one whole-batch pass.
    """
    grad_fn = jax.value_and_grad(cdt_loss, has_aux=True)
    size = jnp.shape(batch["mask"])[0]
    n = micro_batches(size, micro_batch)
    if n == 1:
        return grad_fn(params, log_temperature, cfg, batch, key)
    norms = loss_normalisers(batch)
    (loss, aux), grads = sum_over_passes(
        lambda part, k: grad_fn(params, log_temperature, cfg, part, k, norms), batch, n, key)
    # Every slice reports the same temperature; the sum counts it n times.
    aux = {**aux, "temperature": aux["temperature"] / n}
    return (loss, aux), grads


def sum_over_passes(fn: Callable, batch: Any, n: int, key: jax.Array | None) -> Any:
    """`sum_i fn(slice_i, key_i)` over `n` equal slices of `batch` along its leading axis, one
    `lax.scan` step per slice (so one slice's activations are alive at a time); `key_i` =
    `fold_in(key, i)`, None when `key` is None. `batch` is a pytree of arrays; `fn` returns a
    pytree of arrays (e.g. a loss and its gradient, already divided by the whole batch's
    counts, so that the sum is the whole batch's)."""
    size = jax.tree.leaves(batch)[0].shape[0]
    slices = jax.tree.map(lambda v: jnp.reshape(v, (n, size // n, *jnp.shape(v)[1:])), batch)

    def one(i, part):
        return fn(part, None if key is None else jax.random.fold_in(key, i))

    def body(total, xs):
        return jax.tree.map(jnp.add, total, one(*xs)), None

    first = jax.eval_shape(one, 0, jax.tree.map(lambda v: v[0], slices))
    zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), first)
    total, _ = jax.lax.scan(body, zeros, (jnp.arange(n), slices))
    return total


def make_train_step(
    cfg: CDTConfig, optim: OptimConfig | None = None, micro_batch: int = 0
) -> Callable[[TrainState, Mapping[str, jax.Array], jax.Array], tuple[TrainState, dict]]:
    """A pure `step(state, batch, key) -> (state, aux)` (wrap it in `jax.jit`).

    As in OSRL: one AdamW step on `cdt_loss`, then one Adam step on the temperature loss using
    the entropy of the same forward pass. `aux` is `cdt_loss`'s plus `loss` and
    `temperature_loss`. With `micro_batch` > 0 a larger batch's gradient is computed in passes
    of at most that many windows (`batch_gradients`); the optimiser takes one step on the
    whole batch either way.
    """
    txs = make_optimizer(optim)

    def step(state: TrainState, batch: Mapping[str, jax.Array], key: jax.Array):
        (loss, aux), grads = batch_gradients(
            state.params, state.log_temperature, cfg, batch, key, micro_batch
        )
        updates, opt_state = txs.model.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)

        t_loss, t_grad = jax.value_and_grad(temperature_loss)(
            state.log_temperature, aux["entropy"], cfg
        )
        t_updates, t_state = txs.temperature.update(t_grad, state.temperature_opt_state)
        log_t = optax.apply_updates(state.log_temperature, t_updates)
        new = TrainState(params, opt_state, log_t, t_state, state.step + 1)
        return new, {**aux, "loss": loss, "temperature_loss": t_loss}

    return step
