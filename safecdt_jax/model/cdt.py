"""OSRL's Constrained Decision Transformer (CDT) as a pure Flax (linen) function.

Per timestep the model reads four tokens in the order (return-to-go, cost-to-go, state, action),
each a linear embedding plus a shared learned absolute-timestep embedding (the return and cost
inputs optionally as piecewise-linear ramps and per step left: `model.tokens`). A stack of pre-LN
causal blocks follows; the state token's output feeds a diagonal-Gaussian action head, the action
token's output feeds a 2-class step-cost classifier and an optional next-state head.

Initialisation follows OSRL: every Dense and Embed weight ~ N(0, 0.02^2), biases 0, LayerNorms at
identity. Deviation: PyTorch's `MultiheadAttention` keeps Xavier-uniform on its fused q/k/v
`in_proj`; here q, k and v are separate Dense layers (so LoRA can address them by name) and get
N(0, 0.02^2) like everything else.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from typing import Any

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from safecdt_jax.model.config import CDTConfig
from safecdt_jax.model.tokens import piecewise_linear, steps_left_scale

Params = dict[str, Any]

_W_INIT = nn.initializers.normal(stddev=0.02)
_B_INIT = nn.initializers.zeros


class _Dense(nn.Dense):
    """`nn.Dense` (same params; the same outputs up to float summation order) that multiplies as
    one 2-D matrix product.

    The leading axes are flattened first, so XLA sees `[B*N, D_in] @ [D_in, D_out]`. On the
    CPU that is what makes the backward fast: the weight gradient of a [B, N, D] input contracts
    two axes, which XLA:CPU runs about 3x slower than the same product with one
    (`benchmarks/update_profile.py`).
    """

    @nn.compact
    def __call__(self, inputs: jax.Array) -> jax.Array:
        lead = inputs.shape[:-1]
        flat = super().__call__(inputs.reshape(-1, inputs.shape[-1]))
        return flat.reshape(*lead, self.features)


def _dense(features: int, name: str) -> nn.Dense:
    return _Dense(features, kernel_init=_W_INIT, bias_init=_B_INIT, name=name)


_SITES = ("attn", "residual_attn", "residual_mlp")  # a block's dropout sites, in order of use


def _dropout_shapes(cfg: CDTConfig, b: int, k: int) -> dict[str, tuple[int, ...]]:
    """Shape of every dropout mask of one forward pass by site name (`embed`, then
    `block_{i}/{attn,residual_attn,residual_mlp}`), in the order they are used."""
    n, d = 4 * k, cfg.embed_dim
    shapes = {"embed": (b, n, d)}
    for i in range(cfg.num_layers):
        site = (b, cfg.num_heads, n, n), (b, n, d), (b, n, d)  # attention probs, 2 residuals
        shapes |= {f"block_{i}/{name}": s for name, s in zip(_SITES, site, strict=True)}
    return shapes


def _dropout_noise(key: jax.Array, shapes: dict[str, tuple[int, ...]]) -> dict[str, jax.Array]:
    """Uniform 16-bit integers (uint16, 0..65535) for all dropout masks from ONE draw, by site.

    One draw instead of one per site: with JAX's (default) partitionable threefry each RNG call
    adds seconds of XLA compile time on CPU. 16 bits per mask entry, two from every 32-bit word
    of threefry: the RNG is the update's largest cost after the matrix products on the CPU
    (`benchmarks/update_profile.py`), and 16 bits set a rate of 0.1 to within 1e-5.
    """
    sizes = [math.prod(s) for s in shapes.values()]
    total = sum(sizes)
    words = jax.random.bits(key, ((total + 1) // 2,), jnp.uint32)
    flat = jax.lax.bitcast_convert_type(words, jnp.uint16).reshape(-1)[:total]
    parts = jnp.split(flat, np.cumsum(sizes)[:-1])
    return {name: u.reshape(s) for (name, s), u in zip(shapes.items(), parts, strict=True)}


def _dropout(x: jax.Array, rate: float, u: jax.Array | None) -> jax.Array:
    """Inverted dropout (as PyTorch): zero with probability `rate` (to 16-bit resolution: an
    entry is dropped when its uint16 noise `u` is below round(rate * 2^16)), scale the rest by
    1/(1-rate)."""
    if u is None or rate == 0.0:
        return x
    threshold = min(round(rate * 65536), 65535)
    return jnp.where(u >= threshold, x / (1.0 - rate), 0.0).astype(x.dtype)


class _Attention(nn.Module):
    """Multi-head self-attention with separate `query`/`key`/`value`/`out` projections."""

    cfg: CDTConfig

    @nn.compact
    def __call__(self, x: jax.Array, rows: jax.Array, allowed: jax.Array,
                 u: jax.Array | None) -> jax.Array:
        """Attention of the query tokens `rows` [B, Q, D] over all tokens `x` [B, N, D];
        `allowed` [B, Q, N]. Q = N in the full pass, 1 for the newest action only."""
        cfg = self.cfg
        b, _, d = x.shape

        def heads(y):
            return y.reshape(b, y.shape[1], cfg.num_heads, cfg.head_dim)

        q = heads(_dense(d, "query")(rows))
        k = heads(_dense(d, "key")(x))
        v = heads(_dense(d, "value")(x))
        logits = jnp.einsum("bqhd,bkhd->bhqk", q, k) / math.sqrt(cfg.head_dim)
        # Replace (not add) disallowed logits by a finite minimum: a query row whose keys are all
        # masked (a left-padded slot) then gets uniform weights instead of NaN, and valid rows
        # give masked keys exactly zero weight.
        logits = jnp.where(allowed[:, None], logits, jnp.finfo(logits.dtype).min)
        probs = jax.nn.softmax(logits, axis=-1)
        probs = _dropout(probs, cfg.attention_dropout, u)
        out = jnp.einsum("bhqk,bkhd->bqhd", probs, v).reshape(b, rows.shape[1], d)
        return _dense(d, "out")(out)


class _Block(nn.Module):
    """Pre-LN transformer block: x + drop(attn(LN(x))), then x + drop(MLP(LN(x)))."""

    cfg: CDTConfig

    @nn.compact
    def __call__(self, x: jax.Array, allowed: jax.Array, noise: Mapping[str, jax.Array | None],
                 query: int | None = None) -> jax.Array:
        """The block on all tokens, or (`query` given) only token `query`'s output [B, 1, D]:
        keys and values still come from every token, the rest of the block from that one."""
        cfg = self.cfg
        h = nn.LayerNorm(epsilon=cfg.layernorm_eps, name="ln1")(x)
        rows = h
        if query is not None:
            x, rows, allowed = x[:, query:query + 1], h[:, query:query + 1], \
                allowed[:, query:query + 1]
        h = _Attention(cfg, name="attn")(h, rows, allowed, noise["attn"])
        x = x + _dropout(h, cfg.residual_dropout, noise["residual_attn"])
        h = nn.LayerNorm(epsilon=cfg.layernorm_eps, name="ln2")(x)
        h = _dense(cfg.mlp_ratio * cfg.embed_dim, "mlp_in")(h)
        h = _dense(cfg.embed_dim, "mlp_out")(nn.gelu(h, approximate=False))
        return x + _dropout(h, cfg.residual_dropout, noise["residual_mlp"])


class CDT(nn.Module):
    """The CDT network; use `init_cdt` / `apply_cdt` rather than this module directly."""

    cfg: CDTConfig

    @nn.compact
    def __call__(self, batch: Mapping[str, jax.Array], train: bool,
                 newest_only: bool = False) -> dict[str, jax.Array]:
        """The outputs of every position, or (`newest_only`, evaluation) only `action_mean`
        [B, 1, act] of the newest step (position K-1), its last block computed for that one
        state token: about 40% fewer FLOPs per env step with 2 layers."""
        cfg = self.cfg
        if newest_only and train:
            raise ValueError("the CDT's newest_only pass is for evaluation (train=False)")
        valid = jnp.asarray(batch["mask"]).astype(bool)  # [B, K]
        b, k = valid.shape

        def clean(x, fill=0):
            # Padded slots may hold anything (NaN, out-of-range timesteps); neutralise them so
            # masked keys carry finite values (0 * NaN would leak through the softmax).
            x = jnp.asarray(x)
            return jnp.where(valid.reshape(valid.shape + (1,) * (x.ndim - 2)), x, fill)

        rtg = clean(batch["returns_to_go"]).astype(jnp.float32)
        ctg = clean(batch["costs_to_go"]).astype(jnp.float32)
        if cfg.token_rates:
            scale = steps_left_scale(clean(batch["timesteps"]), cfg.episode_len)
            rtg, ctg = rtg * scale, ctg * scale
        if cfg.token_bins:
            if not (cfg.return_edges and cfg.cost_edges):
                raise ValueError("CDTConfig.token_bins > 0 needs fitted return_edges and "
                                 "cost_edges (safecdt_jax.model.with_token_edges)")
            rtg = piecewise_linear(rtg, cfg.return_edges)
            ctg = piecewise_linear(ctg, cfg.cost_edges)
        else:
            rtg, ctg = rtg[..., None], ctg[..., None]
            if cfg.cost_transform:
                ctg = cfg.cost_offset - ctg
        states = clean(batch["states"]).astype(jnp.float32)
        actions = clean(batch["actions"]).astype(jnp.float32)
        t = jnp.clip(clean(batch["timesteps"]).astype(jnp.int32), 0, cfg.num_timestep_rows - 1)

        d = cfg.embed_dim
        time_emb = nn.Embed(cfg.num_timestep_rows, d, embedding_init=_W_INIT, name="embed_time")(t)
        tokens = jnp.stack(
            [
                _dense(d, "embed_return")(rtg),
                _dense(d, "embed_cost")(ctg),
                _dense(d, "embed_state")(states),
                _dense(d, "embed_action")(actions),
            ],
            axis=2,
        )
        tokens = tokens + time_emb[:, :, None]  # [B, K, 4, D]
        x = tokens.reshape(b, 4 * k, d)  # R_0, C_0, s_0, a_0, R_1, ...
        x = nn.LayerNorm(epsilon=cfg.layernorm_eps, name="embed_norm")(x)
        shapes = _dropout_shapes(cfg, b, k)
        if train:
            noise = _dropout_noise(self.make_rng("dropout"), shapes)
        else:
            noise = dict.fromkeys(shapes)  # evaluation: every dropout is the identity
        x = _dropout(x, cfg.embedding_dropout, noise["embed"])

        # allowed[b, q, k]: causal over the 4K tokens, and key k belongs to a valid step.
        token_valid = jnp.repeat(valid, 4, axis=1)  # a step's 4 tokens share its flag
        causal = jnp.tril(jnp.ones((4 * k, 4 * k), dtype=bool))
        allowed = causal[None] & token_valid[:, None, :]
        for i in range(cfg.num_layers):
            mine = {site: noise[f"block_{i}/{site}"] for site in _SITES}
            last = newest_only and i == cfg.num_layers - 1
            x = _Block(cfg, name=f"block_{i}")(x, allowed, mine, 4 * (k - 1) + 2 if last else None)
        x = nn.LayerNorm(epsilon=cfg.layernorm_eps, name="out_norm")(x)
        if newest_only:  # x is the newest state token's output [B, 1, D]
            out = {"action_mean": _dense(cfg.act_dim, "action_mean")(x)}
            if cfg.stochastic_actions:
                out["action_log_std"] = _dense(cfg.act_dim, "action_log_std")(x)
            return out
        x = x.reshape(b, k, 4, d)
        state_out, action_out = x[:, :, 2], x[:, :, 3]

        out = {
            "action_mean": _dense(cfg.act_dim, "action_mean")(state_out),
            "action_log_std": _dense(cfg.act_dim, "action_log_std")(state_out),
            "cost_log_probs": jax.nn.log_softmax(_dense(2, "cost_head")(action_out), axis=-1),
        }
        if cfg.use_state_head:
            out["next_state"] = _dense(cfg.obs_dim, "state_head")(action_out)
        return out


def dummy_batch(cfg: CDTConfig, batch_size: int = 1) -> dict[str, jax.Array]:
    """An all-zero, all-valid batch of shape [batch_size, seq_len, ...] (for init and tests)."""
    b, k = batch_size, cfg.seq_len
    return {
        "states": jnp.zeros((b, k, cfg.obs_dim), jnp.float32),
        "actions": jnp.zeros((b, k, cfg.act_dim), jnp.float32),
        "returns_to_go": jnp.zeros((b, k), jnp.float32),
        "costs_to_go": jnp.zeros((b, k), jnp.float32),
        "timesteps": jnp.broadcast_to(jnp.arange(k, dtype=jnp.int32), (b, k)),
        "mask": jnp.ones((b, k), jnp.float32),
    }


def init_cdt(key: jax.Array, cfg: CDTConfig) -> Params:
    """Initialise the CDT parameters: a plain nested dict of float32 arrays (no Flax wrapper).

    Every `kernel` and `embedding` ~ N(0, 0.02^2), every `bias` 0, every LayerNorm `scale` 1 (the
    same rule the modules' own initialisers state). Top-level keys: `embed_{return,cost,state,
    action,time}`, `embed_norm`, `block_{i}` (each with `ln1`, `attn/{query,key,value,out}`, `ln2`,
    `mlp_in`, `mlp_out`), `out_norm`, `action_mean`, `action_log_std`, `cost_head` and, when
    enabled, `state_head`. Same key -> same bits.
    """
    return _init_jit(key, cfg)


@functools.partial(jax.jit, static_argnums=1)
def _init_jit(key: jax.Array, cfg: CDTConfig) -> Params:
    # All weights come from ONE normal draw: one RNG call per parameter (as Flax's init does)
    # costs seconds of XLA compile time on CPU with partitionable threefry.
    paths, treedef = jax.tree_util.tree_flatten_with_path(param_shapes(cfg))
    is_weight = [path[-1].key in ("kernel", "embedding") for path, _ in paths]
    sizes = [math.prod(leaf.shape) for (_, leaf), w in zip(paths, is_weight, strict=True) if w]
    noise = 0.02 * jax.random.normal(key, (sum(sizes),), jnp.float32)
    chunks = iter(jnp.split(noise, np.cumsum(sizes)[:-1]))
    leaves = []
    for (path, leaf), weight in zip(paths, is_weight, strict=True):
        if weight:
            leaves.append(next(chunks).reshape(leaf.shape))
        else:  # LayerNorm scale at 1, every bias at 0
            leaves.append(jnp.full(leaf.shape, path[-1].key == "scale", jnp.float32))
    return jax.tree_util.tree_unflatten(treedef, leaves)


def apply_cdt(
    params: Params,
    cfg: CDTConfig,
    batch: Mapping[str, jax.Array],
    train: bool = False,
    key: jax.Array | None = None,
) -> dict[str, jax.Array]:
    """Run the CDT on a batch of context windows.

    Args:
        params: from `init_cdt` (or `merge_lora`).
        cfg: the model's config (static under `jit`).
        batch: `states [B,K,obs]`, `actions [B,K,act]`, `returns_to_go [B,K]` (scaled RTG),
            `costs_to_go [B,K]` (raw CTG; the model applies the cost transform), `timesteps [B,K]`
            (int, absolute step in the episode, clipped into the embedding table),
            `mask [B,K]` (1 = valid step, 0 = padding). Any K works; training uses `cfg.seq_len`.
        train: apply dropout (needs `key`).
        key: PRNG key for dropout; ignored when `train` is False.

    Returns:
        `action_mean [B,K,act]` and `action_log_std [B,K,act]` (raw Gaussian parameters,
        unclipped, read from the state token), `cost_log_probs [B,K,2]` (log-softmax over "step
        cost 0 / 1", from the action token) and, if `cfg.use_state_head`, `next_state [B,K,obs]`.
        Outputs at padded positions are finite but meaningless.
    """
    if train and key is None:
        raise ValueError("apply_cdt(train=True) needs a PRNG key for dropout")
    rngs = {"dropout": key} if train else {}
    return CDT(cfg).apply({"params": params}, batch, train=train, rngs=rngs)


def last_action(params: Params, cfg: CDTConfig, batch: Mapping[str, jax.Array]) -> jax.Array:
    """Deterministic evaluation action `[B, act]` for the newest step of a left-padded window.

    The window holds the last <= K steps at its right end (`mask` 1 there) and padding at the
    left; the current step's action slot is a dummy (its token comes after the state token, so it
    cannot influence the prediction). Returns the Gaussian mean at position K-1, clipped to
    `[-max_action, max_action]`; equal to running the model on the unpadded prefix.
    """
    mean = apply_cdt(params, cfg, batch, train=False)["action_mean"][:, -1]
    return jnp.clip(mean, -cfg.max_action, cfg.max_action)


def newest_action(params: Params, cfg: CDTConfig, batch: Mapping[str, jax.Array],
                  key: jax.Array | None = None) -> jax.Array:
    """`last_action` through the trimmed pass (`CDT(newest_only=True)`): the same action [B, act]
    to float rounding, with the last block computed for the newest state token only. What the
    rollouts call every env step. Only valid for windows whose newest step is real.

    With `cfg.stochastic_actions` the action is a sample `mean + exp(log_std) * N(0, 1)` of the
    Gaussian head, drawn with `key` (required then), clipped to the action box."""
    out = CDT(cfg).apply({"params": params}, batch, train=False, newest_only=True)
    action = out["action_mean"][:, 0]
    if cfg.stochastic_actions:
        if key is None:
            raise ValueError("newest_action with CDTConfig.stochastic_actions needs a PRNG key")
        noise = jax.random.normal(key, action.shape, action.dtype)
        action = action + jnp.exp(out["action_log_std"][:, 0]) * noise
    return jnp.clip(action, -cfg.max_action, cfg.max_action)


def count_params(tree: Any) -> int:
    """Total number of scalars in a pytree of arrays or `jax.ShapeDtypeStruct`s."""
    return int(sum(math.prod(getattr(x, "shape", np.shape(x))) for x in jax.tree.leaves(tree)))


def param_shapes(cfg: CDTConfig) -> Params:
    """The parameter pytree as `ShapeDtypeStruct`s, without allocating or computing anything."""

    def init(key):
        variables = CDT(cfg).init({"params": key}, dummy_batch(cfg), train=False)
        # unfreeze: a plain (mutable, nested) dict whatever Flax's FrozenDict setting is.
        return flax.core.unfreeze(variables["params"])

    return jax.eval_shape(init, jax.random.key(0))
