"""Traced programs stored on disk: the same bits as tracing, no tracing on a warm start."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from deploy_helpers import TINY_DEPLOY, tiny_setup

from safecdt_jax import programs
from safecdt_jax.deploy import make_spec, make_variant, seed_keys, stack_specs, sweep

TRACES = []


def _adam_step(params, opt_state, x):
    """One Adam step on a quadratic; counts its own tracings in TRACES."""
    TRACES.append(1)
    grads = jax.grad(lambda p: jnp.sum((p["w"] * x - 1.0) ** 2))(params)
    updates, opt_state = optax.adam(0.1).update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def _no_export(*args, **kwargs):
    raise AssertionError("traced again: the stored program was not used")


def _assert_same(got, expect):
    assert jax.tree.structure(got) == jax.tree.structure(expect)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expect), strict=True):
        assert np.asarray(a).dtype == np.asarray(b).dtype
        np.testing.assert_array_equal(a, b)


@pytest.fixture
def stored(tmp_path):
    """Storing on, in a fresh folder, with no program loaded in this process yet."""
    programs.enable(tmp_path)
    programs._callers.clear()
    yield tmp_path
    programs.enable(None)
    programs._callers.clear()


def _args():
    params = {"w": jnp.arange(3.0)}
    return params, optax.adam(0.1).init(params), jnp.float32(2.0)


def test_a_stored_program_gives_the_same_bits_without_tracing(stored, monkeypatch):
    jitted = jax.jit(_adam_step, donate_argnums=0)
    expect = jax.device_get(jax.jit(_adam_step)(*_args()))
    first = programs.cached(jitted, _args(), name="adam", static="v1", donate=(0,))
    assert len(list(stored.glob("*.bin"))) == 1
    programs._callers.clear()  # as a new process would: only the file is left
    monkeypatch.setattr(programs, "_export", _no_export)
    warm = programs.cached(jitted, _args(), name="adam", static="v1", donate=(0,))
    for call in (first, warm):
        args = _args()
        _assert_same(jax.device_get(call(*args)), expect)
        assert args[0]["w"].is_deleted() and not args[2].is_deleted()  # donated as asked


def test_the_key_changes_with_static_shapes_and_dtypes():
    params, opt, x = _args()
    key = programs.program_key("adam", "v1", (params, opt, x))
    assert key == programs.program_key("adam", "v1", _args())
    assert key != programs.program_key("adam", "v2", (params, opt, x))
    assert key != programs.program_key("other", "v1", (params, opt, x))
    longer = {"w": jnp.arange(4.0)}
    assert key != programs.program_key("adam", "v1", (longer, optax.adam(0.1).init(longer), x))
    assert key != programs.program_key("adam", "v1", (params, opt, jnp.int32(2)))
    assert key != programs.program_key("adam", "v1", (params, opt, 2.0))  # weakly typed
    with jax.default_matmul_precision("highest"):  # lowers the dots differently
        assert key != programs.program_key("adam", "v1", (params, opt, x))
    assert len(programs.source_digest()) == 64


def test_a_torn_file_is_traced_again(stored):
    jitted = jax.jit(_adam_step)
    programs.cached(jitted, _args(), name="adam", static="v1")
    (path,) = stored.glob("*.bin")
    path.write_bytes(path.read_bytes()[:100])
    programs._callers.clear()
    with pytest.warns(UserWarning, match="unreadable"):
        again = programs.cached(jitted, _args(), name="adam", static="v1")
    _assert_same(jax.device_get(again(*_args())), jax.device_get(jitted(*_args())))
    assert path.stat().st_size > 100  # rewritten whole


def test_storing_off_returns_the_jitted_function():
    programs.enable(None)
    jitted = jax.jit(_adam_step)
    assert programs.cached(jitted, _args(), name="adam", static="v1") is jitted


def test_arguments_of_another_structure_are_refused(stored):
    call = programs.cached(jax.jit(_adam_step), _args(), name="adam", static="v1")
    params, opt, x = _args()
    with pytest.raises(TypeError, match="stored program"):
        call({"v": params["w"]}, opt, x)


def test_a_sweep_from_a_stored_program_equals_the_traced_sweep(stored, monkeypatch):
    env, params, model_cfg, base = tiny_setup()
    keys = seed_keys(3, 2)
    specs = stack_specs([make_spec(make_variant(v, TINY_DEPLOY), 2.0, 4.0)
                         for v in ("safe_cdt", "scheduler_only")])
    run = lambda: jax.device_get(sweep(keys, base, params, specs, env=env,
                                       model_cfg=model_cfg, cfg=TINY_DEPLOY, chunk=2))
    exported = run()  # traces, stores, runs the stored program
    assert len(list(stored.glob("*.bin"))) == 1
    programs._callers.clear()
    with monkeypatch.context() as m:
        m.setattr(programs, "_export", _no_export)
        loaded = run()  # loads the file
    programs.enable(None)
    traced = run()
    _assert_same(exported, traced)
    _assert_same(loaded, traced)
