"""Piecewise-linear return/cost tokens: ramps, fitted edges, and what the LayerNorm keeps."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.model import (
    CDTConfig,
    apply_cdt,
    dummy_batch,
    fit_edges,
    init_cdt,
    piecewise_linear,
    with_nominal_edges,
    with_token_edges,
)
from safecdt_jax.model.tokens import steps_left_scale

SIZES = dict(obs_dim=5, act_dim=2, episode_len=30)


def test_piecewise_linear_known_values():
    got = piecewise_linear(jnp.array([-1.0, 0.5, 1.5, 3.0, 9.0]), (0.0, 1.0, 2.0, 4.0))
    want = [[0, 0, 0], [0.5, 0, 0], [1, 0.5, 0], [1, 1, 0.5], [1, 1, 1]]
    np.testing.assert_allclose(got, want, atol=1e-7)


def test_fit_edges_quantiles_merge_repeats_and_weights():
    # Half the steps share a cost-to-go of 0: the low quantiles merge into one edge.
    values = np.r_[np.zeros(50), np.arange(50.0)]
    edges = fit_edges(values, 8)
    assert edges[0] == 0.0 and edges[-1] == 49.0
    assert all(b > a for a, b in itertools.pairwise(edges))
    assert len(edges) == 5  # 9 quantiles, 4 of them 0
    # Zero weights remove values; weights move the quantiles towards the heavy values.
    assert fit_edges(np.r_[0.0, 1.0, 2.0, 100.0], 2, weights=np.r_[1, 1, 1, 0.0])[-1] == 2.0
    light, heavy = (fit_edges(np.arange(10.0), 2, weights=w)[1]
                    for w in (np.ones(10), np.r_[np.ones(5), 9 * np.ones(5)]))
    assert heavy > light
    assert fit_edges(np.full(7, 3.0), 4) == (3.0, 4.0)


@pytest.mark.parametrize("values, weights, match", [
    (np.array([]), None, "non-empty"),
    (np.array([1.0, np.nan]), None, "finite"),
    (np.array([1.0, 2.0]), np.array([0.0, 0.0]), "weights"),
    (np.array([1.0, 2.0]), np.array([1.0]), "weights"),
])
def test_fit_edges_rejects_bad_input(values, weights, match):
    with pytest.raises(ValueError, match=match):
        fit_edges(values, 4, weights)


@pytest.mark.parametrize("fields, match", [
    (dict(token_bins=-1), "token_bins"),
    (dict(token_bins=4, cost_edges=(1.0, 0.0)), "cost_edges"),
    (dict(token_bins=4, return_edges=(1.0,)), "return_edges"),
    (dict(token_bins=0, return_edges=(0.0, 1.0)), "return_edges"),
    (dict(token_bins=1, cost_edges=(0.0, 1.0, 2.0)), "cost_edges"),
    (dict(token_bins=4, cost_edges=(0.0, float("inf"))), "cost_edges"),
])
def test_bad_edges_name_their_field(fields, match):
    with pytest.raises(ValueError, match=match):
        CDTConfig.preset("tiny", **SIZES, **fields)


def test_unfitted_edges_are_a_clear_error():
    cfg = CDTConfig.preset("tiny", **SIZES, token_bins=4)
    with pytest.raises(ValueError, match="fitted return_edges"):
        init_cdt(jax.random.key(0), cfg)


def test_with_token_edges_scales_like_the_model_inputs():
    cfg = CDTConfig.preset("tiny", **SIZES, token_bins=2, reward_scale=0.1, cost_scale=0.5)
    fitted = with_token_edges(cfg, np.array([0.0, 10.0, 20.0]), np.array([0.0, 4.0, 8.0]))
    assert fitted.return_edges == (0.0, 1.0, 2.0) and fitted.cost_edges == (0.0, 2.0, 4.0)
    linear = CDTConfig.preset("tiny", **SIZES)
    assert with_token_edges(linear, np.ones(3), np.ones(3)) is linear


def _normed_cost_token(params, cfg, ctg):
    """The cost token after the embedding LayerNorm (at init: scale 1, bias 0), timestep 0."""
    x = jnp.asarray(ctg, jnp.float32)
    if cfg.token_bins:
        x = piecewise_linear(x, cfg.cost_edges)
    else:
        x = (cfg.cost_offset - x)[..., None]
    e = params["embed_cost"]
    y = x @ e["kernel"] + e["bias"] + params["embed_time"]["embedding"][0]
    y = y - y.mean(-1, keepdims=True)
    return y / jnp.linalg.norm(y, axis=-1, keepdims=True)


def test_ramps_keep_cost_targets_apart_through_the_layernorm():
    # At init, the linear encoding 5 - 0.1 CTG (the cpu preset's before its ramps) maps
    # cost-to-go 0, 10 and 20 to nearly one direction after the LayerNorm (only the sign of
    # 50 - CTG survives the normalisation); the ramps give each its own.
    ctg = np.array([0.0, 10.0, 20.0]) * 0.1
    linear = CDTConfig.preset("cpu", **SIZES, token_bins=0)
    ramps = with_token_edges(CDTConfig.preset("cpu", **SIZES, token_bins=16),
                             np.zeros(1), np.linspace(0, 100, 101))
    cos = {}
    for name, cfg in (("linear", linear), ("ramps", ramps)):
        tok = _normed_cost_token(init_cdt(jax.random.key(0), cfg), cfg, ctg)
        cos[name] = np.asarray(tok @ tok.T)[np.triu_indices(3, 1)]
    assert cos["linear"].min() > 0.98 and cos["ramps"].max() < 0.9, cos


def test_model_with_ramps_reads_its_tokens_and_is_deterministic():
    cfg = with_token_edges(CDTConfig.preset("tiny", **SIZES, token_bins=4),
                           np.linspace(0, 40, 41), np.linspace(0, 80, 81))
    params = init_cdt(jax.random.key(0), cfg)
    batch = dummy_batch(cfg, 2)
    low = apply_cdt(params, cfg, {**batch, "costs_to_go": jnp.full((2, cfg.seq_len), 1.0)})
    high = apply_cdt(params, cfg, {**batch, "costs_to_go": jnp.full((2, cfg.seq_len), 7.0)})
    again = apply_cdt(params, cfg, {**batch, "costs_to_go": jnp.full((2, cfg.seq_len), 7.0)})
    assert not np.allclose(low["action_mean"], high["action_mean"])
    np.testing.assert_array_equal(high["action_mean"], again["action_mean"])


def test_steps_left_scale_known_values():
    # T / max(T - t, 1) with T = 10: the plain value at t = 0, twice it half-way, capped at 10x.
    np.testing.assert_allclose(steps_left_scale(jnp.array([0, 5, 9, 12]), 10), [1, 2, 10, 10])


def test_rate_edges_need_timesteps_and_use_them():
    cfg = CDTConfig.preset("tiny", **SIZES, token_bins=1, token_rates=True, reward_scale=1.0,
                           cost_scale=1.0)
    with pytest.raises(ValueError, match="timesteps"):
        with_token_edges(cfg, np.ones(2), np.ones(2))
    # A policy earning 1 per step (RTG 30 - t over a 30-step episode) has a constant rate of 30.
    t = np.arange(30)
    fitted = with_token_edges(cfg, 30.0 - t, np.r_[np.zeros(15), np.ones(15)], timesteps=t)
    np.testing.assert_allclose(fitted.return_edges, (30.0, 31.0), rtol=1e-6)


def test_rates_make_a_late_small_rtg_read_like_a_whole_episode():
    # A return-to-go of 5 at t = 20 of 30 (a fast policy's last third) reads as 15 per episode,
    # the same token as a return-to-go of 15 at t = 0; without rates it reads like 5 at t = 0.
    # (Ramps, because a linear embedding with zero bias keeps only the sign of the value.)
    cfg = CDTConfig.preset("tiny", **SIZES, token_rates=True, token_bins=4,
                           return_edges=(0.0, 5.0, 10.0, 20.0, 40.0), cost_edges=(0.0, 1.0))
    params = init_cdt(jax.random.key(0), cfg)
    batch = {k: v[:, :1] for k, v in dummy_batch(cfg, 1).items()}
    # With the timestep embedding zeroed, only the return token can tell the two apart.
    flat = dict(params, embed_time={"embedding": jnp.zeros_like(
        params["embed_time"]["embedding"])})
    late, start = (apply_cdt(flat, cfg, {**batch, "returns_to_go": jnp.full((1, 1), r),
                                         "timesteps": jnp.full((1, 1), t)})["action_mean"]
                   for r, t in ((5.0, 20), (15.0, 0)))
    np.testing.assert_allclose(late, start, atol=1e-6)
    plain = cfg.replace(token_rates=False)
    late, start = (apply_cdt(flat, plain, {**batch, "returns_to_go": jnp.full((1, 1), r),
                                           "timesteps": jnp.full((1, 1), t)})["action_mean"]
                   for r, t in ((5.0, 20), (15.0, 0)))
    assert not np.allclose(late, start, atol=1e-6)


def test_nominal_edges_span_the_scaled_ranges_and_leave_linear_tokens_alone():
    cfg = with_nominal_edges(CDTConfig.preset("cpu", **SIZES), max_return=60.0, max_cost=100.0)
    assert cfg.token_bins == 16 and len(cfg.return_edges) == len(cfg.cost_edges) == 17
    # The model reads RTG x 0.1 and CTG x 0.1 (the cpu preset's scales).
    assert cfg.return_edges[0] == 0.0 and cfg.return_edges[-1] == pytest.approx(6.0)
    assert cfg.cost_edges[0] == 0.0 and cfg.cost_edges[-1] == pytest.approx(10.0)
    linear = CDTConfig.preset("cpu", **SIZES, token_bins=0)
    assert with_nominal_edges(linear) is linear


def test_a_span_keeps_targets_below_the_data_apart():
    """Cost labels from 12.7 up: without a span every target below 12.7 is the same input, with
    the span (0, 100) the targets 6 and 12 differ, and the data still get their quantile bins."""
    values = np.linspace(12.7, 69.0, 200)
    plain = fit_edges(values, 16)
    assert np.array_equal(piecewise_linear(jnp.array(6.0), plain),
                          piecewise_linear(jnp.array(12.0), plain))
    spanned = fit_edges(values, 16, span=(0.0, 100.0))
    assert len(spanned) == 17 and spanned[0] == 0.0 and spanned[-1] == 100.0
    np.testing.assert_allclose(spanned[1:-1], fit_edges(values, 14), rtol=1e-6)
    assert not np.array_equal(piecewise_linear(jnp.array(6.0), spanned),
                              piecewise_linear(jnp.array(12.0), spanned))
    assert fit_edges(values, 16, span=(20.0, 50.0)) == plain  # a span inside the data adds none
    with pytest.raises(ValueError, match="span must be two finite numbers lo < hi"):
        fit_edges(values, 16, span=(5.0, 5.0))
    with pytest.raises(ValueError, match="leave none for the values"):
        fit_edges(values, 2, span=(0.0, 100.0))
