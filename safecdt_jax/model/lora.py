"""Functional LoRA for the CDT: adapters are a separate pytree, merged into ordinary params.

For every block `i` and every target projection `p` in `cfg.lora_targets` (default query and
value) the adapter pytree holds `lora[f"block_{i}"]["attn"][p] = {"A": [D, r], "B": [r, D]}`,
mirroring the path of the adapted kernel in the base params. With Flax's `y = x @ W + b`
convention the merged kernel is `W + (alpha / r) * A @ B`, i.e. `y = x W + (alpha/r) x A B + b`.

Training adapters only needs no freezing machinery: take gradients of
`loss(merge_lora(base, lora, cfg))` with respect to `lora`; the base params are a constant.
A leading axis on every adapter leaf (one adapter set per seed) works with `jax.vmap`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp

from safecdt_jax.model.cdt import Params, apply_cdt
from safecdt_jax.model.config import CDTConfig

Lora = dict[str, Any]


def init_lora(key: jax.Array, params: Params, cfg: CDTConfig) -> Lora:
    """Fresh adapters for the `cfg.lora_targets` projections of every block.

    `A [D_in, r]` ~ Uniform(-1/sqrt(D_in), 1/sqrt(D_in)), the bound that PyTorch's
    `kaiming_uniform_(a=sqrt(5))` gives and that HuggingFace PEFT uses for LoRA's A; `B [r, D_out]`
    is zero, so the merged model equals the base model at init. `params` may be arrays or
    `ShapeDtypeStruct`s (only shapes and dtypes are read). Same key -> same bits.
    """
    r = cfg.lora_rank
    lora: Lora = {}
    names = [f"block_{i}" for i in range(cfg.num_layers)]
    keys = jax.random.split(key, len(names) * len(cfg.lora_targets))
    for i, name in enumerate(names):
        adapters = {}
        for j, target in enumerate(cfg.lora_targets):
            kernel = params[name]["attn"][target]["kernel"]
            d_in, d_out = kernel.shape
            bound = 1.0 / math.sqrt(d_in)
            sub = keys[i * len(cfg.lora_targets) + j]
            adapters[target] = {
                "A": jax.random.uniform(sub, (d_in, r), kernel.dtype, -bound, bound),
                "B": jnp.zeros((r, d_out), kernel.dtype),
            }
        lora[name] = {"attn": adapters}
    return lora


def merge_lora(params: Params, lora: Lora, cfg: CDTConfig) -> Params:
    """Ordinary CDT params with every adapted kernel replaced by `W + (alpha/r) * A @ B`.

    Pure: `params` is not modified; untouched sub-trees are shared, not copied.
    """
    scale = cfg.lora_scale

    def merge(p: Mapping[str, Any], a: Mapping[str, Any]) -> dict[str, Any]:
        if set(a) == {"A", "B"}:
            return {**p, "kernel": p["kernel"] + scale * (a["A"] @ a["B"])}
        unknown = set(a) - set(p)
        if unknown:
            raise KeyError(f"LoRA adapters for unknown params {sorted(unknown)}")
        return {k: merge(v, a[k]) if k in a else v for k, v in p.items()}

    return merge(params, lora)


def apply_cdt_lora(
    params: Params,
    lora: Lora,
    cfg: CDTConfig,
    batch: Mapping[str, jax.Array],
    train: bool = False,
    key: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """`apply_cdt` on the merged params `merge_lora(params, lora, cfg)` (same outputs/shapes)."""
    return apply_cdt(merge_lora(params, lora, cfg), cfg, batch, train, key)


def lora_param_count(cfg: CDTConfig) -> int:
    """Adapter scalars for `cfg`: layers x targets x (D*r + r*D) (65,536 for `paper`)."""
    d, r = cfg.embed_dim, cfg.lora_rank
    return cfg.num_layers * len(cfg.lora_targets) * (d * r + r * d)
