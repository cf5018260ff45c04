"""Online LoRA finetuning: adapters-only updates, variants as data, weighted loss, one program."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safecdt_jax.data import buffer_add, buffer_init, sample_windows
from safecdt_jax.deploy import (
    DeployConfig,
    adapter_gradient,
    init_adapter_opt,
    lora_finetune,
    lora_loss,
    make_variant,
    replay_weights,
    stack_variants,
)
from safecdt_jax.model import (
    CDTConfig,
    apply_cdt_lora,
    init_cdt,
    init_lora,
    merge_lora,
    with_nominal_edges,
)

T, OBS, ACT = 12, 3, 2
MCFG = CDTConfig.preset("tiny", OBS, ACT, T)
# A larger lr than the default 1e-4 so a few steps move the loss visibly; same code path.
CFG = DeployConfig(lora_steps=4, lora_batch=16, lora_lr=3e-3)
BUDGET = 3.0  # the test episodes cost about 6: early windows exceed it, so weights vary
finetune = jax.jit(lora_finetune, static_argnames=("model_cfg", "cfg"))
loss_fn = jax.jit(lora_loss, static_argnames="model_cfg")


def run(key, lora, opt, base, buf, variant, lam=5.0):
    return finetune(key, lora, opt, base, MCFG, buf, jnp.float32(lam), jnp.float32(BUDGET),
                    variant, cfg=CFG)


@pytest.fixture(scope="module")
def base():
    # Larger weights than the 0.02 init (a pretrained model's scale), so adapters matter.
    p = init_cdt(jax.random.key(0), MCFG)
    return jax.tree.map(lambda x: x * 10.0 if x.ndim == 2 else x, p)


@pytest.fixture(scope="module")
def buf():
    rng = np.random.default_rng(0)
    b = buffer_init(4, T, OBS, ACT)
    for length in (12, 9, 12):
        b = buffer_add(b, {
            "observations": rng.normal(size=(T, OBS)),
            "actions": rng.uniform(-1, 1, size=(T, ACT)),
            "rewards": rng.uniform(0, 1, size=T),
            "costs": (rng.uniform(size=T) < 0.6).astype(np.float32),
        }, length)
    return b


@pytest.fixture(scope="module")
def lora(base):
    return init_lora(jax.random.key(1), base, MCFG)


def leaves_equal(a, b):
    return all(np.array_equal(np.asarray(x), np.asarray(y))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def test_finetune_changes_only_the_adapters(base, buf, lora):
    base_copy = jax.tree.map(np.array, base)
    opt = init_adapter_opt(lora, CFG)
    new, new_opt, aux = run(jax.random.key(2), lora, opt, base, buf, make_variant("safe_cdt"))
    assert leaves_equal(base, base_copy)  # the frozen params are untouched
    assert not leaves_equal(new, lora)
    assert int(new_opt[0].count) == CFG.lora_steps
    assert aux["loss"].shape == (CFG.lora_steps,) and np.isfinite(aux["loss"]).all()
    assert 0.0 < float(aux["weight_min"].min()) < 1.0  # some sequences exceed B and lam = 5
    # The effective model differs from the base only in the adapted q/v kernels.
    before, after = merge_lora(base, lora, MCFG), merge_lora(base, new, MCFG)
    changed = {jax.tree_util.keystr(path)
               for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(before),
                                       jax.tree.leaves(after), strict=True)
               if not np.array_equal(x, y)}
    assert changed == {f"['block_{i}']['attn']['{t}']['kernel']"
                       for i in range(MCFG.num_layers) for t in ("query", "value")}


@pytest.mark.parametrize("name", ["zero_shot", "scheduler_only", "fixed_ctg(0.3)"])
def test_lora_off_leaves_adapters_bit_identical(base, buf, lora, name):
    opt = init_adapter_opt(lora, CFG)
    new, new_opt, _ = run(jax.random.key(2), lora, opt, base, buf, make_variant(name))
    assert leaves_equal(new, lora) and leaves_equal(new_opt, opt)


def test_projected_excess_changes_only_the_weights_of_cut_episodes(base, buf, lora):
    realised = CFG.replace(replay_excess="realised")  # CFG projects (the default)
    opt, variant = init_adapter_opt(lora, CFG), make_variant("safe_cdt")

    def over_budget(b, c):  # per step, the share of windows whose excess is positive
        return finetune(jax.random.key(2), lora, opt, base, MCFG, b, jnp.float32(5.0),
                        jnp.float32(BUDGET), variant, cfg=c)[2]["excess_fraction"]

    # the fixture's second episode stopped at step 9 of 12: projected, its late windows (little
    # realised cost left) still read the overrun, so more windows count as over the budget
    assert float(over_budget(buf, CFG).sum()) > float(over_budget(buf, realised).sum())
    full = buffer_init(4, T, OBS, ACT)  # full-length episodes only: the two rules agree
    for i in (0, 2):
        full = buffer_add(full, {k: getattr(buf, k)[i] for k in
                                 ("observations", "actions", "rewards", "costs")}, T)
    np.testing.assert_array_equal(over_budget(full, CFG), over_budget(full, realised))


def test_empty_buffer_is_a_no_op(base, lora):
    opt = init_adapter_opt(lora, CFG)
    empty = buffer_init(4, T, OBS, ACT)
    new, new_opt, aux = run(jax.random.key(2), lora, opt, base, empty, make_variant("safe_cdt"))
    assert leaves_equal(new, lora) and leaves_equal(new_opt, opt)
    assert np.isfinite(aux["loss"]).all()


def test_loss_decreases_on_a_fixed_buffer(base, buf, lora):
    fixed = sample_windows(jax.random.key(9), buf, 64, MCFG.seq_len, None,
                           MCFG.reward_scale, MCFG.cost_scale)
    ones = jnp.ones(64)
    losses = [float(loss_fn(lora, base, MCFG, fixed, ones))]
    current, opt, variant = lora, init_adapter_opt(lora, CFG), make_variant("naive_lora")
    for i in range(4):  # four episodes' worth of finetuning rounds
        current, opt, _ = run(jax.random.key(10 + i), current, opt, base, buf, variant)
        losses.append(float(loss_fn(current, base, MCFG, fixed, ones)))
    assert all(b < a for a, b in itertools.pairwise(losses)), losses
    assert losses[-1] < 0.95 * losses[0], losses


def test_lora_loss_is_the_weighted_masked_mean(base, buf, lora):
    win = sample_windows(jax.random.key(3), buf, 32, MCFG.seq_len, None, 0.1, 1.0)
    mask = np.asarray(win.mask)
    assert (mask == 0).any()  # some windows run past their episode's end
    weights = replay_weights(win.costs_to_go[:, 0], mask[:, 0] > 0, 2.0, BUDGET, CFG)
    lora_b = jax.tree.map(lambda x: x + 0.1, lora)  # non-zero B: a non-trivial merged model
    got = float(loss_fn(lora_b, base, MCFG, win, weights))
    apply = jax.jit(lambda lo, batch: apply_cdt_lora(base, lo, MCFG, batch)["action_mean"])
    mean = np.asarray(apply(lora_b, win._asdict()))
    sq = ((mean - np.asarray(win.actions)) ** 2).sum(-1)
    per_window = (sq * mask).sum(1) / mask.sum(1)
    np.testing.assert_allclose(got, (np.asarray(weights) * per_window).mean(), rtol=1e-5)
    # Garbage in padded action slots does not reach the loss.
    dirty = win._replace(actions=jnp.where(win.mask[..., None] > 0, win.actions, 1e6))
    np.testing.assert_allclose(float(loss_fn(lora_b, base, MCFG, dirty, weights)), got,
                               rtol=1e-6)


def test_gradient_in_passes_is_the_one_pass_gradient(base, buf, lora):
    """Passes of 4 windows divide by the whole batch's valid count: with the invalid windows
    all in the first pass (per-pass means would differ), loss and gradient equal one pass's."""
    win = sample_windows(jax.random.key(3), buf, 16, MCFG.seq_len, None, 0.1, 1.0)
    win = win._replace(mask=win.mask.at[:3].set(0.0))  # 3 invalid windows, all in pass 0
    weights = jnp.linspace(0.2, 1.0, 16)
    lora_b = jax.tree.map(lambda x: x + 0.1, lora)
    grad = jax.jit(adapter_gradient, static_argnames=("model_cfg", "micro_batch"))
    whole = grad(lora_b, base, MCFG, win, weights, None, micro_batch=0)
    passes = grad(lora_b, base, MCFG, win, weights, None, micro_batch=4)
    assert not leaves_equal(whole[1], jax.tree.map(jnp.zeros_like, whole[1]))
    for x, y in zip(jax.tree.leaves(passes), jax.tree.leaves(whole), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-7)
    # ... and the finetuning round with them keeps the same adapters to float rounding.
    opt = init_adapter_opt(lora, CFG)
    one = finetune(jax.random.key(6), lora, opt, base, MCFG, buf, jnp.float32(5.0),
                   jnp.float32(BUDGET), make_variant("safe_cdt"), cfg=CFG)[0]
    four = finetune(jax.random.key(6), lora, opt, base, MCFG, buf, jnp.float32(5.0),
                    jnp.float32(BUDGET), make_variant("safe_cdt"),
                    cfg=CFG.replace(lora_micro_batch=4))[0]
    assert not leaves_equal(one, lora)
    for x, y in zip(jax.tree.leaves(four), jax.tree.leaves(one), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="lora_micro_batch"):
        DeployConfig(lora_micro_batch=-1)


def test_stacked_variants_vmap_through_one_compiled_finetune(base, buf, lora):
    traces = []

    def counted(key, variant, lora, opt, base, buf, lam):
        traces.append(1)  # once per trace
        return lora_finetune(key, lora, opt, base, MCFG, buf, lam, jnp.float32(BUDGET),
                             variant, CFG)

    vrun = jax.jit(jax.vmap(counted, in_axes=(None, 0, None, None, None, None, None)))
    opt = init_adapter_opt(lora, CFG)
    key, lam = jax.random.key(4), jnp.float32(5.0)
    outs = {}
    for names in (["safe_cdt", "zero_shot"], ["no_reweight", "scheduler_only"]):
        variants = stack_variants([make_variant(n) for n in names])
        new, new_opt, aux = vrun(key, variants, lora, opt, base, buf, lam)
        for i, n in enumerate(names):
            outs[n] = (jax.tree.map(lambda x, i=i: x[i], new),
                       jax.tree.map(lambda x, i=i: x[i], new_opt),
                       jax.tree.map(lambda x, i=i: x[i], aux))
    assert len(traces) == 1
    for n in ("zero_shot", "scheduler_only"):
        assert leaves_equal(outs[n][0], lora) and leaves_equal(outs[n][1], opt)
    for n in ("safe_cdt", "no_reweight"):
        assert not leaves_equal(outs[n][0], lora)
    assert float(outs["no_reweight"][2]["weight_min"].min()) == 1.0  # reweighting off
    assert float(outs["safe_cdt"][2]["weight_min"].min()) < 1.0
    # The vmapped lane equals the unbatched run of the same variant.
    single, _, _ = run(key, lora, opt, base, buf, make_variant("safe_cdt"), lam=5.0)
    for x, y in zip(jax.tree.leaves(outs["safe_cdt"][0]), jax.tree.leaves(single), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)


def test_adapter_gradient_skips_the_frozen_weights_gradients():
    """Differentiating w.r.t. the adapters alone computes no weight gradient of the frozen base:
    XLA's FLOP count of the LoRA step is about two forwards (the forward and the backward to the
    activations, plus the merged q/v kernels' gradient), where the full-parameter gradient costs
    about three. The deployment's FLOP floor counts the LoRA step this way."""
    from safecdt_jax.data.windows import Windows
    from safecdt_jax.model import dummy_batch

    cfg = with_nominal_edges(CDTConfig.preset("cpu", 72, 2, 1000))
    params = init_cdt(jax.random.key(0), cfg)
    adapters = init_lora(jax.random.key(1), params, cfg)
    b = dummy_batch(cfg, 32)
    zeros = jnp.zeros((32,), jnp.int32)
    win = Windows(b["states"], b["actions"], b["returns_to_go"], b["costs_to_go"],
                  jnp.zeros((32, cfg.seq_len)), b["timesteps"], b["mask"], zeros, zeros)
    w = jnp.ones((32,))

    def flops(fn, *args):
        cost = jax.jit(fn).lower(*args).compile().cost_analysis()
        return (cost[0] if isinstance(cost, list) else cost)["flops"]

    forward = flops(lambda a: lora_loss(a, params, cfg, win, w), adapters)
    adapter_grad = flops(jax.grad(lambda a: lora_loss(a, params, cfg, win, w)), adapters)
    full_grad = flops(jax.grad(lambda p: lora_loss(adapters, p, cfg, win, w)), params)
    assert adapter_grad / forward < 2.5 < full_grad / forward


def test_seeds_in_turn_match_the_batched_seeds_and_a_loop(base, buf, lora):
    """`lora_in_turn` loops over the vmapped seeds instead of batching them: the adapters
    agree with the batched program to float rounding and with a loop of single-seed calls."""
    keys = jax.random.split(jax.random.key(5), 3)
    loras = jax.vmap(lambda k: init_lora(k, base, MCFG))(keys)
    opts = jax.vmap(lambda lo: init_adapter_opt(lo, CFG))(loras)
    variant, lam = make_variant("safe_cdt"), jnp.float32(5.0)

    def seeds(cfg):
        one = lambda k, lo, op: lora_finetune(k, lo, op, base, MCFG, buf, lam,
                                              jnp.float32(BUDGET), variant, cfg)
        return jax.jit(jax.vmap(one))(keys, loras, opts)[0]

    batched, in_turn = seeds(CFG.replace(lora_in_turn=False)), seeds(CFG.replace(lora_in_turn=True))
    assert not leaves_equal(in_turn, loras)  # the steps ran
    for x, y in zip(jax.tree.leaves(in_turn), jax.tree.leaves(batched), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    for i, k in enumerate(keys):
        pick = lambda t, i=i: jax.tree.map(lambda leaf: leaf[i], t)
        single = run(k, pick(loras), pick(opts), base, buf, variant)[0]
        for a, b in zip(jax.tree.leaves(pick(in_turn)), jax.tree.leaves(single), strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    # Under the sweep's two vmaps (runs x seeds) both axes run in turn (two more loops in the
    # program than the batched one), with the same result.
    lams = jnp.asarray([5.0, 0.5])

    def runs(cfg):
        one = lambda lam, k, lo, op: lora_finetune(k, lo, op, base, MCFG, buf, lam,
                                                   jnp.float32(BUDGET), variant, cfg)
        return jax.jit(jax.vmap(jax.vmap(one, (None, 0, 0, 0)), (0, None, None, None)))

    programs = {on: runs(CFG.replace(lora_in_turn=on)) for on in (False, True)}
    loops = {on: f.lower(lams, keys, loras, opts).as_text().count("stablehlo.while")
             for on, f in programs.items()}
    assert loops[True] == loops[False] + 2, loops
    nested, flat = (programs[on](lams, keys, loras, opts)[0] for on in (True, False))
    for x, y in zip(jax.tree.leaves(nested), jax.tree.leaves(flat), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="lora_in_turn"):
        DeployConfig(lora_in_turn="yes")


def test_seeds_in_turn_by_default_on_one_cpu_device_only():
    """`lora_in_turn` None resolves per device set: on for one CPU device (these tests'),
    off with the seeds sharded over several; an explicit choice is kept."""
    cpu = jax.devices("cpu")[0]
    assert DeployConfig().lora_in_turn is None
    assert DeployConfig().resolved([cpu]).lora_in_turn is True
    assert DeployConfig().resolved([cpu, cpu]).lora_in_turn is False
    assert DeployConfig(lora_in_turn=False).resolved([cpu]).lora_in_turn is False
    assert DeployConfig().resolved().lora_in_turn is (jax.default_backend() == "cpu"
                                                      and jax.device_count() == 1)
