"""Traced programs kept on disk (`jax.export`), so a warm start skips JAX's tracing.

XLA's persistent cache saves the compile of a program, not the Python-side tracing and
lowering that come before it: for the main job's deployment program (a scan over episodes of a
1,000-step rollout scan and the LoRA steps, vmapped over runs and seeds) those took 5.6 s of a
warm start on 2026-12-01 and 13-16 s on 2026-12-03 (2-core Intel Xeon), against 0.6-1.7 s to
load the compiled code. `cached(jitted, args, static=...)` exports the traced program once
(StableHLO plus the output's pytree structure) into `folder/KEY.bin` and, on a later start,
calls the stored program instead of tracing the Python function again; the same XLA cache then
serves its compile.

The key covers everything the traced program depends on: `static` (the caller's description of
the static arguments, e.g. the reprs of the env and configs), the arguments' pytree structure,
shapes and dtypes, the backend and device count, the JAX, jaxlib, MuJoCo and Flax versions, and
a digest of this package's source files, so any edit to the code traces afresh. A stored
program runs the same StableHLO the tracing would give, so results are the same bits (tested
in tests/test_programs.py).
"""

from __future__ import annotations

import functools
import hashlib
import os
import pickle
import tempfile
import warnings
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import Any

import jax
import numpy as np

_FORMAT = 1
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


def _versions() -> str:
    import flax
    import jaxlib
    import mujoco

    return f"jax {jax.__version__} jaxlib {jaxlib.__version__} mujoco {mujoco.__version__} " \
           f"flax {flax.__version__} x64 {jax.config.jax_enable_x64}"


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
    text = "\n".join([str(_FORMAT), name, static, str(tree), shapes, devices, _versions(),
                      source_digest()])
    return hashlib.sha256(text.encode()).hexdigest()


def _write_atomic(path: Path, payload: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise


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
        out_tree = stored["out_tree"]
    except Exception as err:  # a torn or foreign file: trace afresh and overwrite it
        warnings.warn(f"stored program {path} unreadable ({err}); tracing again", stacklevel=3)
        return None

    def call(*args):
        return jax.tree.unflatten(out_tree, exported.call(*jax.tree.leaves(args)))

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
    if _folder is None or jax.device_count() > 1:
        return jitted
    path = _folder / f"{program_key(name, repr(static), args)}.bin"
    if path.exists():
        caller = _caller(path, donate)
        if caller is not None:
            return caller
    exported, out_tree = _export(jitted, args, donate)
    _write_atomic(path, pickle.dumps({"format": _FORMAT, "exported": exported.serialize(),
                                      "out_tree": out_tree}))
    return _caller(path, donate) or jitted
