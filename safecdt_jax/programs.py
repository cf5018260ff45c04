"""Traced programs kept on disk (`jax.export`), so a warm start skips JAX's tracing.

XLA's persistent cache saves the compile of a program, not the Python-side tracing and
lowering that come before it: for the main job's deployment program (a scan over episodes of a
1,000-step rollout scan and the LoRA steps, vmapped over runs and seeds) those took 5.6 s of a
warm start on 2026-12-01 and 13-16 s on 2026-12-03 (2-core Intel Xeon), against 0.6-1.7 s to
load the compiled code. `cached(jitted, args, static=...)` exports the traced program once
(StableHLO plus the output's pytree structure) into `folder/KEY.bin` and, on a later start,
calls the stored program instead of tracing the Python function again; the same XLA cache then
serves its compile.

The key covers what the traced program depends on: `static` (the caller's description of the
static arguments, e.g. the reprs of the env and configs), the arguments' pytree structure,
shapes, dtypes and weak types, the backend and device count, the versions of jax, jaxlib,
mujoco, mujoco-mjx, flax, optax and numpy, every JAX option except those about caches, logs
and tracebacks, and a digest of this package's source files, so any edit to the code traces
afresh. Code outside the package that the program calls (a user's own module) is not in the
key. A stored program runs the same StableHLO the tracing would give, so results are the same
bits (tested in tests/test_programs.py). Whatever cannot be stored (a program with weakly typed
outputs, whose weak types serialisation drops; a failed export or write; `jax_disable_jit` or
NaN checking on) runs traced, as without storing. Files are pickles: keep the folder private.
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import warnings
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from safecdt_jax.io import write_bytes_atomic

_FORMAT = 2
_PACKAGES = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "flax", "optax", "numpy")
# JAX options that cannot change a trace (caches, logs, tracebacks, dumps, profiling) stay out
# of the key, so a test's cache settings and a CLI run's share stored programs; all others go in.
_IGNORED_OPTIONS = ("cache", "log", "traceback", "explain", "persistent", "profil", "dump",
                    "topology")
# Options under which a stored program would skip what the user asked for.
_TRACE_ONLY_OPTIONS = ("jax_disable_jit", "jax_debug_nans", "jax_debug_infs")
_folder: Path | None = None
_callers: dict[tuple[Path, tuple[int, ...]], Callable] = {}


def enable(folder: str | os.PathLike | None) -> None:
    """Store traced programs in `folder` (None: keep nothing, trace every start)."""
    global _folder
    _folder = None if folder is None else Path(folder)


def folder() -> Path | None:
    """The folder traced programs are stored in, or None when storing is off."""
    return _folder


@functools.cache
def source_digest() -> str:
    """SHA-256 (hex) of every `.py` file of the `safecdt_jax` package, by relative path."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _environment() -> str:
    """Library versions and the JAX options a trace depends on, as one string."""
    from importlib.metadata import version

    options = sorted((name, repr(getattr(jax.config, name, value)))
                     for name, value in jax.config.values.items()
                     if not any(word in name for word in _IGNORED_OPTIONS))
    return f"{[(p, version(p)) for p in _PACKAGES]} {options}"


def _leaf_spec(leaf) -> jax.ShapeDtypeStruct:
    """Shape, dtype and weak type of one argument leaf, as `jax.jit` would see it."""
    if isinstance(leaf, jax.Array):
        aval = jax.typeof(leaf)
        return jax.ShapeDtypeStruct(aval.shape, aval.dtype, weak_type=aval.weak_type)
    array = np.asarray(leaf)  # NumPy arrays; Python scalars enter a jit weakly typed
    return jax.ShapeDtypeStruct(array.shape, jax.dtypes.canonicalize_dtype(array.dtype),
                                weak_type=not isinstance(leaf, np.ndarray | np.generic))


def program_key(name: str, static: str, args: tuple) -> str:
    """The file stem (SHA-256 hex) of the traced program `name` for `args` and `static`."""
    leaves, tree = jax.tree.flatten(args)
    shapes = ";".join(f"{s.shape}{s.dtype}{'w' if s.weak_type else ''}"
                      for s in map(_leaf_spec, leaves))
    devices = f"{jax.default_backend()} x{jax.device_count()}"
    text = "\n".join([str(_FORMAT), name, static, str(tree), shapes, devices, _environment(),
                      source_digest()])
    return hashlib.sha256(text.encode()).hexdigest()


def _export(jitted: Callable, args: tuple, donate: tuple[int, ...]) -> tuple[Any, Any]:
    """Trace `jitted` on `args` into an `Exported` over flat leaves; (exported, out tree)."""
    leaves, in_tree = jax.tree.flatten(args)
    # Leaf positions of the donated arguments, so the exported program donates what jitted did.
    sizes = [len(jax.tree.leaves(a)) for a in args]
    starts = [sum(sizes[:i]) for i in range(len(args))]
    donated = tuple(j for i in donate for j in range(starts[i], starts[i] + sizes[i]))
    box = {}

    def flat(*leaves):
        out = jitted(*jax.tree.unflatten(in_tree, leaves))
        out_leaves, box["tree"] = jax.tree.flatten(out)
        return out_leaves

    exported = jax.export.export(jax.jit(flat, donate_argnums=donated))(
        *map(_leaf_spec, leaves))
    return exported, box["tree"]


def _caller(path: Path, donate: tuple[int, ...]) -> Callable | None:
    """The jitted caller of the stored program at `path` (one per process), or None if the
    file cannot be read."""
    if (path, donate) in _callers:
        return _callers[path, donate]
    try:
        stored = pickle.loads(path.read_bytes())
        if stored.get("format") != _FORMAT:
            return None
        exported = jax.export.deserialize(stored["exported"])
        in_tree, out_tree = stored["in_tree"], stored["out_tree"]
    except Exception as err:  # a torn or foreign file: trace afresh and overwrite it
        warnings.warn(f"stored program {path} unreadable ({err}); tracing again", stacklevel=3)
        return None

    def call(*args):
        leaves, tree = jax.tree.flatten(args)
        if tree != in_tree:  # static, so checked once per trace of this wrapper
            raise TypeError(f"stored program {path.name}: arguments {tree}, stored {in_tree}")
        return jax.tree.unflatten(out_tree, exported.call(*leaves))

    # The donation happens here: the exported module's own aliasing does not survive `call`.
    _callers[path, donate] = jax.jit(call, donate_argnums=donate)
    return _callers[path, donate]


def cached(jitted: Callable, args: tuple, *, name: str, static: Hashable,
           donate: tuple[int, ...] = ()) -> Callable:
    """A callable that computes `jitted(*args)` for arguments shaped like `args`.

    With storing enabled (`enable`) and one device, it is the stored program of
    (`name`, `static`, the arguments' structure and shapes, versions, source), exported from
    `jitted` the first time; otherwise `jitted` itself. `static` must describe every static
    input of `jitted` that its arguments do not (its `repr` goes into the key). `donate` lists
    the positional arguments `jitted` donates. Several devices keep `jitted` (the stored
    program holds no shardings).
    """
    if (_folder is None or jax.device_count() > 1
            or any(getattr(jax.config, name) for name in _TRACE_ONLY_OPTIONS)):
        return jitted
    path = _folder / f"{program_key(name, repr(static), args)}.bin"
    if path.exists():
        caller = _caller(path, donate)
        if caller is not None:
            return caller
    try:
        exported, out_tree = _export(jitted, args, donate)
        if any(aval.weak_type for aval in exported.out_avals):
            return jitted  # a stored program would return these strongly typed
        write_bytes_atomic(path, pickle.dumps({
            "format": _FORMAT, "exported": exported.serialize(),
            "in_tree": jax.tree.structure(args), "out_tree": out_tree}))
    except Exception as err:  # e.g. a read-only cache or an op jax.export cannot serialise
        warnings.warn(f"could not store program {name} ({err}); tracing it", stacklevel=2)
        return jitted
    return _caller(path, donate) or jitted
