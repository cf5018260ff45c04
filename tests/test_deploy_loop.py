"""The deployment loop and sweeps: vmap == loop, same key -> same bits, one compile, 2 devices."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from deploy_helpers import TINY_DEPLOY, tiny_setup

from safecdt_jax.deploy import (
    deploy,
    deploy_episodes,
    deploy_init,
    init_adapters,
    make_spec,
    make_variant,
    seed_keys,
    stack_specs,
    sweep,
)
from safecdt_jax.deploy.sweep import _compiled

R_REF = 4.0
BUDGET = 2.0


def _specs(*names, budget=BUDGET):
    return stack_specs([make_spec(make_variant(n, TINY_DEPLOY), budget, R_REF) for n in names])


@pytest.fixture(scope="module")
def swept():
    env, params, model_cfg, base = tiny_setup()
    keys = seed_keys(0, 3)
    specs = _specs("safe_cdt", "zero_shot")
    out = sweep(keys, base, params, specs, env=env, model_cfg=model_cfg, cfg=TINY_DEPLOY)
    return keys, specs, jax.device_get(out)


def _single(key, spec):
    env, params, model_cfg, base = tiny_setup()
    lora = jax.tree.map(lambda x: x[0], init_adapters(key[None], base, model_cfg))
    run = jax.jit(lambda k, lo, s: deploy(k, base, lo, params, s, env=env, model_cfg=model_cfg,
                                          cfg=TINY_DEPLOY))
    return jax.device_get(run(key, lora, spec))


def test_sweep_equals_single_seed_calls(swept):
    # Batched and single programs fuse float ops differently; tiny differences grow along a
    # trajectory (wall contacts, adapter updates), so episodes are compared closely while they
    # are short of that, and the stage decisions (targets, lambda) over the whole deployment.
    keys, specs, out = swept
    for r in range(2):
        spec = jax.tree.map(lambda x, r=r: x[r], specs)
        for s in (0, 2):
            single = _single(keys[s], spec)
            for name, value in single._asdict().items():
                np.testing.assert_allclose(getattr(out, name)[r, s, :3], value[:3], rtol=1e-4,
                                           atol=1e-5, err_msg=f"run {r} seed {s} {name}")
            for name in ("ctg_target", "rtg_target", "violation"):
                np.testing.assert_allclose(getattr(out, name)[r, s], getattr(single, name),
                                           rtol=1e-5, err_msg=f"run {r} seed {s} {name}")


def test_same_key_same_bits(swept):
    keys, specs, out = swept
    env, params, model_cfg, base = tiny_setup()
    again = jax.device_get(sweep(keys, base, params, specs, env=env, model_cfg=model_cfg,
                                 cfg=TINY_DEPLOY))
    for name, value in out._asdict().items():
        np.testing.assert_array_equal(getattr(again, name), value)


def test_sweep_returns_the_final_carry(swept):
    keys, specs, out = swept
    env, params, model_cfg, base = tiny_setup()
    metrics, carry = jax.device_get(sweep(keys, base, params, specs, env=env,
                                          model_cfg=model_cfg, cfg=TINY_DEPLOY,
                                          return_carry=True))
    for name, value in out._asdict().items():  # the same program, the same bits
        np.testing.assert_array_equal(getattr(metrics, name), value)
    np.testing.assert_array_equal(carry.history["costs"], out.costs)  # [runs, seeds, episodes]
    np.testing.assert_array_equal(carry.lam, out.lam[:, :, -1])
    start = init_adapters(keys, base, model_cfg)
    moved = [np.abs(a[0] - b).max() for a, b in zip(jax.tree.leaves(carry.lora),
                                                    jax.tree.leaves(start), strict=True)]
    assert max(moved) > 0  # safe_cdt (run 0) finetuned its adapters


def test_variants_and_budgets_share_one_compilation(swept):
    keys, _, _ = swept
    env, params, model_cfg, base = tiny_setup()
    fn = _compiled(env, model_cfg, TINY_DEPLOY, False)[1]
    before = fn._cache_size()
    sweep(keys, base, params, _specs("naive_lora", "fixed_ctg(0.2)", budget=9.0), env=env,
          model_cfg=model_cfg, cfg=TINY_DEPLOY)
    assert fn._cache_size() == before


def test_sweep_without_lora_variants_skips_the_steps_with_the_same_bits(swept):
    keys, _, _ = swept
    env, params, model_cfg, base = tiny_setup()
    specs = _specs("zero_shot", "fixed_ctg(0.2)")
    # Other test files in this process may have compiled these programs for other shapes, so
    # count what this sweep adds: one no-LoRA compile at most, and no call of the LoRA program.
    no_lora = _compiled(env, model_cfg, TINY_DEPLOY, False, False)[1]
    init_all, run_all = _compiled(env, model_cfg, TINY_DEPLOY, False, True)  # with LoRA steps
    before = no_lora._cache_size(), run_all._cache_size()
    fast = jax.device_get(sweep(keys, base, params, specs, env=env, model_cfg=model_cfg,
                                cfg=TINY_DEPLOY))
    assert no_lora._cache_size() >= 1 and no_lora._cache_size() - before[0] <= 1
    assert run_all._cache_size() == before[1]
    carry = init_all(keys, init_adapters(keys, base, model_cfg), specs)
    _, full = jax.device_get(run_all(carry, np.arange(TINY_DEPLOY.episodes, dtype=np.int32),
                                     base, params, specs))
    for name, value in full._asdict().items():
        np.testing.assert_array_equal(getattr(fast, name), value, err_msg=name)
    assert np.all(fast.lora_loss == 0)


def test_metrics_follow_the_rules(swept):
    _, _, out = swept
    safe, zero = 0, 1
    np.testing.assert_array_equal(out.violation, out.costs > BUDGET)
    assert np.all(out.costs <= BUDGET + 1)  # the runtime budget ends an episode at B + 1
    # zero_shot: fixed CR_0 and RR_0 targets, no lambda.
    np.testing.assert_allclose(out.ctg_target[zero], 0.6 * BUDGET)
    np.testing.assert_allclose(out.rtg_target[zero], 0.5 * R_REF)
    assert np.all(out.lam[zero] == 0)
    # safe_cdt: targets change only at stage starts (every 2 episodes), within the CR bounds.
    ctg = out.ctg_target[safe]
    np.testing.assert_array_equal(ctg[:, 0::2], ctg[:, 1::2])
    assert np.all(ctg >= 0.05 * BUDGET - 1e-5) and np.all(ctg <= BUDGET + 1e-5)
    assert np.any(ctg != 0.6 * BUDGET), "the scheduler never moved the cost target"
    assert np.all(out.lam[safe][:, 0] == 1.0)  # frozen during the warmup


def test_chunked_episodes_equal_one_scan(swept):
    keys, specs, _ = swept
    env, params, model_cfg, base = tiny_setup()
    spec = jax.tree.map(lambda x: x[0], specs)
    lora = jax.tree.map(lambda x: x[0], init_adapters(keys[:1], base, model_cfg))
    static = dict(env=env, model_cfg=model_cfg, cfg=TINY_DEPLOY)
    step = jax.jit(lambda c, e: deploy_episodes(c, e, base, params, spec, **static))
    carry = deploy_init(keys[0], lora, spec, **static)
    parts = []
    for start in (0, 3):
        carry, m = step(carry, np.arange(start, start + 3))
        parts.append(jax.device_get(m))
    single = _single(keys[0], spec)
    np.testing.assert_allclose(np.concatenate([p.costs for p in parts]), single.costs)
    np.testing.assert_allclose(np.concatenate([p.ctg_target for p in parts]), single.ctg_target)


_TWO_DEVICES = textwrap.dedent("""
    import json, sys
    import jax
    from safecdt_jax.deploy import make_spec, make_variant, seed_keys, stack_specs, sweep
    from deploy_helpers import TINY_DEPLOY, tiny_setup
    assert len(jax.devices()) == 2, jax.devices()
    env, params, model_cfg, base = tiny_setup()
    specs = stack_specs([make_spec(make_variant("safe_cdt", TINY_DEPLOY), 2.0, 4.0)])
    out = sweep(seed_keys(0, 3), base, params, specs, env=env, model_cfg=model_cfg,
                cfg=TINY_DEPLOY)
    json.dump({k: v.tolist() for k, v in jax.device_get(out)._asdict().items()}, sys.stdout)
""")


@pytest.mark.slow
def test_two_forced_cpu_devices_match_one(swept):
    _, _, out = swept
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu", PYTHONPATH=os.path.join(root, "tests"))
    proc = subprocess.run([sys.executable, "-c", _TWO_DEVICES], capture_output=True, text=True,
                          env=env, cwd=root, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    two = json.loads(proc.stdout.strip().splitlines()[-1])
    # As in test_sweep_equals_single_seed_calls: close early on, same stage decisions throughout.
    for name in ("costs", "returns", "lam"):
        np.testing.assert_allclose(np.asarray(two[name])[0][:, :3], getattr(out, name)[0][:, :3],
                                   rtol=1e-4, atol=1e-5, err_msg=name)
    np.testing.assert_allclose(np.asarray(two["ctg_target"])[0], out.ctg_target[0], rtol=1e-5)
