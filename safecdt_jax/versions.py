"""The software a result was made with, recorded beside it (checkpoints, results, reports)."""

from __future__ import annotations

import platform
from importlib import metadata as importlib_metadata

# The packages whose versions shape a result (the simulator's ones for env-bound results).
PACKAGES = ("safecdt-jax", "jax", "jaxlib", "flax", "optax", "orbax-checkpoint", "numpy")


def versions(packages: tuple[str, ...] = PACKAGES) -> dict[str, str]:
    """Python, the JAX backend in use and the installed version of each of `packages`."""
    import jax

    out = {"python": platform.python_version(), "backend": jax.default_backend()}
    for name in packages:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out
