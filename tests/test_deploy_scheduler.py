"""Deployment config, variants as data, Wilson-score scheduler, lambda update, replay weights."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.deploy import (
    VARIANT_SPECS,
    DeployConfig,
    lambda_init,
    lambda_update,
    make_variant,
    replay_weights,
    scheduler_init,
    scheduler_step,
    scheduler_update,
    stack_variants,
    stage_ratios,
    targets,
    wilson_lower,
    window_mask,
)

CFG = DeployConfig()
B = 30.0
W = CFG.window


def window(n_ok, n, cost_ok=10.0, cost_bad=50.0):
    """Window arrays [W]: n valid episodes, the first n_ok within budget; garbage past n."""
    i = np.arange(W)
    costs = np.where(i < n_ok, cost_ok, cost_bad)
    costs = np.where(i < n, costs, -1e6)  # invalid slots would count as "ok" if not masked
    return jnp.asarray(costs, jnp.float32), jnp.asarray(i < n)


def returns_window(n_hit, n, target=5.0):
    """Returns [W] and their RTG targets [W]: the first n_hit reach the target."""
    i = np.arange(W)
    returns = np.where(i < n_hit, target + 1.0, target - 1.0)
    returns = np.where(i < n, returns, 1e6)
    return jnp.asarray(returns, jnp.float32), jnp.full((W,), target, jnp.float32)


def update(state, n_ok, n_hit=0, n=W):
    costs, valid = window(n_ok, n)
    returns, rtg = returns_window(n_hit, n)
    return scheduler_update(state, costs, returns, rtg, valid, B, CFG)


# ----------------------------------------------------------------------------- config, variants


def test_config_defaults_match_method_and_are_static():
    c = DeployConfig()
    assert (c.episodes, c.stage_len, c.window, c.z) == (50, 5, 10, 1.0)
    assert (c.tighten_below, c.relax_above, c.cr_step) == (0.5, 0.9, 0.1)
    assert (c.momentum_factor, c.momentum_max, c.cr_min, c.cr_max) == (1.5, 3.0, 0.05, 1.0)
    assert (c.cr0, c.rr0, c.rr_step, c.rr_min, c.rr_max) == (0.6, 0.5, 0.1, 0.1, 1.5)
    assert (c.lambda_warmup, c.violation_target, c.lambda_rise) == (10, 0.1, 5.0)
    assert (c.lambda_max, c.lambda_decay, c.lambda0, c.weight_floor) == (20.0, 0.95, 1.0, 0.1)
    assert (c.lora_steps, c.lora_batch, c.lora_lr) == (10, 32, 1e-4)
    assert (c.clip_ctg, c.budget, c.lora_dropout) == (True, 30.0, False)
    assert c.stop_over_budget is True  # the paper's runtime-budget wrapper
    assert c.replay_excess == "projected"  # the weights see the overrun the budget cut off
    assert hash(c) == hash(DeployConfig()) and c == DeployConfig()
    assert c.replace(episodes=100).episodes == 100


@pytest.mark.parametrize(
    "changes",
    [dict(episodes=0), dict(window=2.5), dict(z=0.0), dict(tighten_below=0.95),
     dict(cr0=1.2), dict(rr_min=0.0), dict(momentum_factor=0.5), dict(lambda0=30.0),
     dict(weight_floor=0.0), dict(lambda_decay=1.5), dict(lambda_warmup=-1),
     dict(replay_excess="total")],
)
def test_config_rejects_invalid_values(changes):
    with pytest.raises(ValueError, match="DeployConfig"):
        DeployConfig(**changes)


@pytest.mark.parametrize(
    "spec, flags, cr1, cr2, switch",
    [
        ("safe_cdt", (1, 1, 1), 0.6, 0.6, 50),
        ("no_reweight", (1, 0, 1), 0.6, 0.6, 50),
        ("scheduler_only", (1, 0, 0), 0.6, 0.6, 50),
        ("zero_shot", (0, 0, 0), 0.6, 0.6, 50),
        ("naive_lora", (0, 0, 1), 0.6, 0.6, 50),
        ("fixed_ctg(0.2)", (0, 0, 0), 0.2, 0.2, 50),
        (" fixed_ctg( 1.0 ) ", (0, 0, 0), 1.0, 1.0, 50),
        ("step_change(0.2,1.0)", (0, 0, 0), 0.2, 1.0, 25),
        ("step_change(1, .2, 40)", (0, 0, 0), 1.0, 0.2, 40),
        ("step_change(0.2->1.0)", (0, 0, 0), 0.2, 1.0, 25),
        ("step_change(0.2→1.0)", (0, 0, 0), 0.2, 1.0, 25),
    ],
)
def test_make_variant_every_spec(spec, flags, cr1, cr2, switch):
    v = make_variant(spec, CFG)
    assert (bool(v.scheduler), bool(v.reweight), bool(v.lora)) == tuple(map(bool, flags))
    assert float(v.cr_first) == pytest.approx(cr1) and float(v.cr_second) == pytest.approx(cr2)
    assert int(v.switch_episode) == switch
    assert v.scheduler.dtype == jnp.bool_ and v.switch_episode.dtype == jnp.int32


def test_step_change_switches_at_half_of_the_configured_deployment():
    v = make_variant("step_change(0.2,1.0)", CFG.replace(episodes=100))
    cr = [float(stage_ratios(scheduler_init(CFG), e, v, CFG)[0]) for e in (0, 49, 50, 99)]
    assert cr == pytest.approx([0.2, 0.2, 1.0, 1.0])


@pytest.mark.parametrize("spec", ["full", "SAFE_CDT", "fixed_ctg()", "step_change(0.2)", ""])
def test_make_variant_unknown_spec_lists_the_valid_ones(spec):
    with pytest.raises(ValueError, match="unknown variant") as err:
        make_variant(spec, CFG)
    assert all(s in str(err.value) for s in VARIANT_SPECS)


@pytest.mark.parametrize("spec", ["fixed_ctg(0.01)", "fixed_ctg(2.0)", "step_change(0.2,1.5)"])
def test_make_variant_rejects_ratios_outside_the_cr_bounds(spec):
    with pytest.raises(ValueError, match="outside"):
        make_variant(spec, CFG)


def test_stage_ratios_and_targets_per_variant():
    state = scheduler_init(CFG).__class__(
        cr=jnp.float32(0.3), rr=jnp.float32(0.8), momentum=jnp.float32(1.0),
        last_dir=jnp.int32(-1), a_c=jnp.float32(0.0), a_r=jnp.float32(0.0))
    cr, rr = stage_ratios(state, 7, make_variant("safe_cdt", CFG), CFG)
    assert (float(cr), float(rr)) == pytest.approx((0.3, 0.8))
    cr, rr = stage_ratios(state, 7, make_variant("zero_shot", CFG), CFG)
    assert (float(cr), float(rr)) == pytest.approx((0.6, 0.5))
    cr, rr = stage_ratios(state, 7, make_variant("fixed_ctg(0.4)", CFG), CFG)
    assert (float(cr), float(rr)) == pytest.approx((0.4, 0.5))
    ctg, rtg = targets(cr, rr, B, 40.0)
    assert (float(ctg), float(rtg)) == pytest.approx((12.0, 20.0))


# ----------------------------------------------------------------------------- Wilson, scheduler


def test_wilson_lower_values():
    k = jnp.array([10, 7, 6, 0, 5])
    n = jnp.array([10, 10, 10, 10, 5])
    # 7/10 is 0.54246 (float64), so 0.542 to 3 decimals (0.543 only if 0.5425 is rounded up).
    np.testing.assert_allclose(wilson_lower(k, n, 1.0), [0.9091, 0.5425, 0.4429, 0.0, 0.8333],
                               atol=1e-4)
    assert float(wilson_lower(0, 0, 1.0)) == 0.0  # n = 0: defined as 0, finite
    # z = 1.96: "relax" (> 0.9) unreachable for any n <= 10 (documented in DeployConfig.z).
    assert max(float(wilson_lower(n, n, 1.96)) for n in range(1, 11)) < 0.9
    # Agrees with the closed form in float64.
    p, z, n_ = 0.7, 1.0, 10
    ref = (p + z * z / (2 * n_) - z * math.sqrt(p * (1 - p) / n_ + z * z / (4 * n_ * n_))) / (
        1 + z * z / n_)
    assert float(wilson_lower(7, 10, 1.0)) == pytest.approx(ref, rel=1e-6)


def test_scheduler_tighten_hold_relax():
    s0 = scheduler_init(CFG)
    s, a_c, _ = update(s0, n_ok=6)  # A_C = 0.443 < 0.5: tighten
    assert float(a_c) == pytest.approx(0.4429, abs=1e-4)
    assert float(s.cr) == pytest.approx(0.5) and int(s.last_dir) == -1
    s, a_c, _ = update(s0, n_ok=7)  # 0.543: hold
    assert float(s.cr) == pytest.approx(0.6) and int(s.last_dir) == 0
    s, a_c, _ = update(s0, n_ok=10)  # 0.909 > 0.9: relax
    assert float(s.cr) == pytest.approx(0.7) and int(s.last_dir) == 1
    s, a_c, _ = update(s0, n_ok=5, n=5)  # 5/5 -> 0.833: hold (relax needs the full window)
    assert float(s.cr) == pytest.approx(0.6)
    s, a_c, _ = update(s0, n_ok=0, n=0)  # empty window: A_C = 0 but no move
    assert float(a_c) == 0.0 and float(s.cr) == pytest.approx(0.6)


def test_budget_and_target_boundaries_count_as_success():
    at = jnp.full((W,), B)  # cost == B is not a violation; return == RTG target is a hit
    _, a_c, a_r = scheduler_update(scheduler_init(CFG), at, at, at, jnp.ones(W, bool), B, CFG)
    assert float(a_c) == pytest.approx(0.9091, abs=1e-4)
    assert float(a_r) == pytest.approx(0.9091, abs=1e-4)


def test_momentum_grows_caps_resets_and_cr_is_clipped():
    s = scheduler_init(CFG)
    crs, ds = [], []
    for _ in range(4):  # repeated tighten
        s, _, _ = update(s, n_ok=0)
        crs.append(float(s.cr))
        ds.append(float(s.momentum))
    assert ds == pytest.approx([1.0, 1.5, 2.25, 3.0])
    # 0.6 -0.1 -0.15 -0.225 = 0.125, then -0.3 clips at cr_min = 0.05
    assert crs == pytest.approx([0.5, 0.35, 0.125, 0.05])
    s, _, _ = update(s, n_ok=0)  # at the bound: stays clipped, momentum stays capped
    assert float(s.cr) == pytest.approx(0.05) and float(s.momentum) == 3.0
    s, _, _ = update(s, n_ok=10)  # direction change: momentum back to 1
    assert float(s.momentum) == 1.0 and float(s.cr) == pytest.approx(0.15)
    s, _, _ = update(s, n_ok=7)  # hold: d <- 1 (METHOD: not a repeat), last direction kept
    assert float(s.momentum) == 1.0 and int(s.last_dir) == 1
    s, _, _ = update(s, n_ok=10)  # same as the last non-zero direction: momentum grows
    assert float(s.momentum) == 1.5 and float(s.cr) == pytest.approx(0.3)
    for _ in range(5):
        s, _, _ = update(s, n_ok=10)
    assert float(s.cr) == pytest.approx(1.0)  # clipped at cr_max


def test_return_ratio_is_cost_prioritised():
    s0 = scheduler_init(CFG)
    s, _, a_r = update(s0, n_ok=7, n_hit=10)  # A_R high but A_C not > 0.9: frozen
    assert float(a_r) > 0.9 and float(s.rr) == pytest.approx(0.5)
    s, _, _ = update(s0, n_ok=0, n_hit=0)  # A_R low, A_C low: frozen too
    assert float(s.rr) == pytest.approx(0.5)
    s, _, _ = update(s0, n_ok=10, n_hit=10)  # gate open, A_R > 0.9: raise
    assert float(s.rr) == pytest.approx(0.6)
    s, _, _ = update(s0, n_ok=10, n_hit=6)  # gate open, A_R < 0.5: lower
    assert float(s.rr) == pytest.approx(0.4)
    s, _, _ = update(s0, n_ok=10, n_hit=8)  # gate open, A_R in between: hold
    assert float(s.rr) == pytest.approx(0.5)
    high = s0.__class__(**{**s0.__dict__, "rr": jnp.float32(1.45)})
    s, _, _ = update(high, n_ok=10, n_hit=10)
    assert float(s.rr) == pytest.approx(1.5)  # clipped at rr_max
    low = s0.__class__(**{**s0.__dict__, "rr": jnp.float32(0.15)})
    s, _, _ = update(low, n_ok=10, n_hit=0)
    assert float(s.rr) == pytest.approx(0.1)  # clipped at rr_min


def test_scheduler_update_jit_equals_eager():
    rng = np.random.default_rng(0)
    step = jax.jit(scheduler_update, static_argnames="cfg")
    s_eager = s_jit = scheduler_init(CFG)
    for _ in range(8):
        costs = jnp.asarray(rng.uniform(0, 45, W), jnp.float32)
        rets = jnp.asarray(rng.uniform(0, 10, W), jnp.float32)
        rtg = jnp.asarray(rng.uniform(0, 10, W), jnp.float32)
        valid = jnp.asarray(np.arange(W) < rng.integers(1, W + 1))
        s_eager, ac_e, ar_e = scheduler_update(s_eager, costs, rets, rtg, valid, B, CFG)
        s_jit, ac_j, ar_j = step(s_jit, costs, rets, rtg, valid, B, cfg=CFG)
        for a, b in zip(jax.tree.leaves((s_eager, ac_e, ar_e)),
                        jax.tree.leaves((s_jit, ac_j, ar_j)), strict=True):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_scheduler_step_updates_only_at_stage_ends_and_only_when_on():
    costs, valid = window(0, W)  # would tighten
    returns, rtg = returns_window(0, W)
    s0 = scheduler_init(CFG)
    on, off = make_variant("safe_cdt", CFG), make_variant("zero_shot", CFG)
    for e in range(10):
        s, a_c, _ = scheduler_step(s0, e, costs, returns, rtg, valid, B, on, CFG)
        assert float(s.cr) == pytest.approx(0.5 if e in (4, 9) else 0.6)
        assert float(a_c) == pytest.approx(float(wilson_lower(0, W, 1.0)))  # logged every episode
        s, _, _ = scheduler_step(s0, e, costs, returns, rtg, valid, B, off, CFG)
        assert float(s.cr) == pytest.approx(0.6)


def test_window_mask():
    np.testing.assert_array_equal(window_mask(2, 6, 4), [1, 1, 1, 0, 0, 0])
    np.testing.assert_array_equal(window_mask(5, 8, 3), [0, 0, 0, 1, 1, 1, 0, 0])
    assert not np.asarray(window_mask(-1, 4, 10)).any()


# ----------------------------------------------------------------------------- lambda, weights


def violations(n_bad, n=W):
    i = np.arange(W)
    return jnp.asarray((i < n_bad) | (i >= n)), jnp.asarray(i < n)  # invalid slots "violate"


def test_lambda_rises_decays_caps_and_waits_for_warmup():
    bad, valid = violations(5)  # v = 0.5
    for e in range(9):  # episodes 0..8: fewer than 10 finished
        assert float(lambda_update(1.0, bad, valid, e, CFG)) == 1.0
    assert float(lambda_update(1.0, bad, valid, 9, CFG)) == pytest.approx(1.0 + 5.0 * 0.4)
    assert float(lambda_update(19.0, bad, valid, 30, CFG)) == 20.0  # capped
    ok, valid = violations(1)  # v = 0.1 = v*: not above target -> decay
    assert float(lambda_update(2.0, ok, valid, 30, CFG)) == pytest.approx(1.9)
    none, valid = violations(0)
    assert float(lambda_update(0.0, none, valid, 30, CFG)) == 0.0  # stays >= 0
    bad3, valid3 = violations(1, n=3)  # 1 of 3 valid (masked slots ignored): v = 1/3
    assert float(lambda_update(0.0, bad3, valid3, 30, CFG)) == pytest.approx(5 * (1 / 3 - 0.1))
    assert float(lambda_update(1.0, bad, valid, 30, CFG, enabled=False)) == 0.0
    assert float(lambda_init(CFG)) == 1.0 and float(lambda_init(CFG, jnp.bool_(False))) == 0.0


def test_replay_weights_hand_computed():
    ctg = jnp.array([10.0, 30.0, 45.0, 60.0, 150.0])  # excess 0, 0, 15, 30, 120
    raw = np.array([1.0, 1.0, math.exp(-1.0), math.exp(-2.0), 0.1])  # exp(-2*120/30) floored
    w = replay_weights(ctg, jnp.ones(5, bool), 2.0, B, CFG)
    np.testing.assert_allclose(w, raw / raw.mean(), rtol=1e-6)
    assert float(w.mean()) == pytest.approx(1.0)


def test_projected_cost_to_go_extends_a_cut_episode_at_its_rate():
    from safecdt_jax.deploy.reweight import projected_cost_to_go

    # windows of a full episode (length 1000) keep their realised cost-to-go; every window of
    # an episode cut at step 300 with 31 cost gains the 700 missing steps at 31 / 300 per step
    got = projected_cost_to_go(jnp.array([12.0, 31.0, 1.0]), jnp.array([1000, 300, 300]),
                               jnp.array([40.0, 31.0, 31.0]), 1000)
    np.testing.assert_allclose(got, [12.0, 31.0 + 700 * 31 / 300, 1.0 + 700 * 31 / 300],
                               rtol=1e-6)
    # at lambda 2 the cut episode's first window is floored; the realised reading cannot be
    w = replay_weights(got, jnp.ones(3, bool), 2.0, B, CFG)
    assert float(w[1] / w[0]) == pytest.approx(0.1, rel=1e-6)
    realised = replay_weights(jnp.array([12.0, 31.0, 1.0]), jnp.ones(3, bool), 2.0, B, CFG)
    assert float(realised[1] / realised[0]) == pytest.approx(math.exp(-2.0 / B), rel=1e-6)


def test_replay_weights_floor_mask_and_off():
    ctg = jnp.array([0.0, 100.0, 200.0, 5.0, 1e4])
    mask = jnp.array([True, True, True, True, False])
    w = np.asarray(replay_weights(ctg, mask, 20.0, B, CFG))
    assert w[4] == 0.0  # invalid sequence
    np.testing.assert_allclose(w[:4].mean(), 1.0, rtol=1e-6)  # mean 1 over the valid ones
    np.testing.assert_allclose(w[1] / w[0], 0.1, rtol=1e-6)  # floored
    np.testing.assert_allclose(w[2], w[1])
    off = replay_weights(ctg, mask, 20.0, B, CFG, enabled=jnp.bool_(False))
    np.testing.assert_array_equal(off, [1, 1, 1, 1, 0])
    np.testing.assert_array_equal(replay_weights(ctg, mask, 0.0, B, CFG), [1, 1, 1, 1, 0])
    assert np.isfinite(replay_weights(ctg, jnp.zeros(5, bool), 1.0, B, CFG)).all()


# ----------------------------------------------------------------------------- one program


def test_stacked_variants_run_in_one_compiled_program():
    traces = []

    def deploy_bits(variant, state, lam, e, hist_costs, hist_returns, hist_rtg):
        traces.append(1)  # runs once per trace, not per call
        valid = window_mask(e, hist_costs.shape[0], CFG.window)
        state, a_c, _ = scheduler_step(state, e, hist_costs, hist_returns, hist_rtg, valid, B,
                                       variant, CFG)
        lam = lambda_update(lam, hist_costs > B, valid, e, CFG, enabled=variant.reweight)
        cr, rr = stage_ratios(state, e + 1, variant, CFG)
        return cr, rr, lam, a_c

    run = jax.jit(jax.vmap(deploy_bits, in_axes=(0, None, None, None, None, None, None)))
    hist = jnp.where(jnp.arange(50) % 2 == 0, 50.0, 10.0)  # half the episodes violate
    args = (scheduler_init(CFG), jnp.float32(1.0), 9, hist, hist, hist)
    names = ["safe_cdt", "zero_shot", "fixed_ctg(0.2)", "naive_lora"]
    cr, rr, lam, _ = run(stack_variants([make_variant(n, CFG) for n in names]), *args)
    np.testing.assert_allclose(cr, [0.5, 0.6, 0.2, 0.6], rtol=1e-6)
    np.testing.assert_allclose(rr, 0.5)
    np.testing.assert_allclose(lam, [3.0, 0.0, 0.0, 0.0], rtol=1e-6)
    names = ["no_reweight", "step_change(0.4,0.8,10)", "scheduler_only", "safe_cdt"]
    cr, _, lam, _ = run(stack_variants([make_variant(n, CFG) for n in names]), *args)
    np.testing.assert_allclose(cr, [0.5, 0.8, 0.5, 0.5], rtol=1e-6)
    np.testing.assert_allclose(lam, [0.0, 0.0, 0.0, 3.0], rtol=1e-6)
    assert len(traces) == 1
