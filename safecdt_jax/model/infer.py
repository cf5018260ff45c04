"""A faster evaluation-only forward pass for the newest action of a window (rollouts).

`last_action` runs the whole CDT and reads one output. The rollout needs only the action of the
newest state token, so the last block only has to process that one query: its keys and values
still come from every token, but its attention output, MLP and heads are computed for a single
position instead of 4K. With 2 layers this removes about 40% of the forward FLOPs per env step.
Same params pytree as `cdt.py`; `tests/test_model_infer.py` checks it equals `last_action`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import jax
import jax.numpy as jnp

from safecdt_jax.model.cdt import Params
from safecdt_jax.model.config import CDTConfig


def _dense(p: Mapping, x: jax.Array) -> jax.Array:
    return x @ p["kernel"] + p["bias"]


def _layer_norm(p: Mapping, x: jax.Array, eps: float) -> jax.Array:
    mean = x.mean(-1, keepdims=True)
    var = jnp.square(x - mean).mean(-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps) * p["scale"] + p["bias"]


def _attend(p: Mapping, h: jax.Array, rows: jax.Array, allowed: jax.Array,
            cfg: CDTConfig) -> jax.Array:
    """Multi-head attention of query rows `rows` [B, Q, D] over all tokens `h` [B, N, D]."""
    b, n, d = h.shape
    q = _dense(p["query"], rows).reshape(b, rows.shape[1], cfg.num_heads, cfg.head_dim)
    k = _dense(p["key"], h).reshape(b, n, cfg.num_heads, cfg.head_dim)
    v = _dense(p["value"], h).reshape(b, n, cfg.num_heads, cfg.head_dim)
    logits = jnp.einsum("bqhd,bkhd->bhqk", q, k) / math.sqrt(cfg.head_dim)
    logits = jnp.where(allowed[:, None], logits, jnp.finfo(logits.dtype).min)
    out = jnp.einsum("bhqk,bkhd->bqhd", jax.nn.softmax(logits, axis=-1), v)
    return _dense(p["out"], out.reshape(b, rows.shape[1], d))


def _block(p: Mapping, x: jax.Array, allowed: jax.Array, query: slice | None,
           cfg: CDTConfig) -> jax.Array:
    """Pre-LN block; with `query` only those token positions are computed and returned."""
    h = _layer_norm(p["ln1"], x, cfg.layernorm_eps)
    if query is not None:
        x, rows, allowed = x[:, query], h[:, query], allowed[:, query]
    else:
        rows = h
    x = x + _attend(p["attn"], h, rows, allowed, cfg)
    h = _layer_norm(p["ln2"], x, cfg.layernorm_eps)
    h = _dense(p["mlp_out"], jax.nn.gelu(_dense(p["mlp_in"], h), approximate=False))
    return x + h


def newest_action(params: Params, cfg: CDTConfig, batch: Mapping[str, jax.Array]) -> jax.Array:
    """Deterministic action [B, act] of the newest step of left-padded windows (evaluation mode).

    Same inputs and result as `cdt.last_action`: the Gaussian mean read from the state token of
    position K-1, clipped to `[-max_action, max_action]`. Only valid for windows whose newest
    step (position K-1) is real.
    """
    valid = jnp.asarray(batch["mask"]).astype(bool)
    b, k = valid.shape

    def clean(x):
        x = jnp.asarray(x)
        return jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - 2)), x, 0)

    rtg = clean(batch["returns_to_go"]).astype(jnp.float32)[..., None]
    ctg = clean(batch["costs_to_go"]).astype(jnp.float32)[..., None]
    if cfg.cost_transform:
        ctg = cfg.cost_offset - ctg
    t = jnp.clip(clean(batch["timesteps"]).astype(jnp.int32), 0, cfg.num_timestep_rows - 1)
    tokens = jnp.stack([
        _dense(params["embed_return"], rtg),
        _dense(params["embed_cost"], ctg),
        _dense(params["embed_state"], clean(batch["states"]).astype(jnp.float32)),
        _dense(params["embed_action"], clean(batch["actions"]).astype(jnp.float32)),
    ], axis=2) + params["embed_time"]["embedding"][t][:, :, None]
    x = _layer_norm(params["embed_norm"], tokens.reshape(b, 4 * k, cfg.embed_dim),
                    cfg.layernorm_eps)
    token_valid = jnp.repeat(valid, 4, axis=1)
    causal = jnp.tril(jnp.ones((4 * k, 4 * k), dtype=bool))
    allowed = causal[None] & token_valid[:, None, :]
    state_token = 4 * (k - 1) + 2  # the newest step's state token
    for i in range(cfg.num_layers):
        last = i == cfg.num_layers - 1
        query = slice(state_token, state_token + 1) if last else None
        x = _block(params[f"block_{i}"], x, allowed, query, cfg)
    x = _layer_norm(params["out_norm"], x[:, 0], cfg.layernorm_eps)
    mean = _dense(params["action_mean"], x)
    return jnp.clip(mean, -cfg.max_action, cfg.max_action)
