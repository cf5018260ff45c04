"""Shared test setup: CPU only, and one persistent compilation cache for every test process."""

import os
from pathlib import Path

CACHE_DIR = Path(__file__).resolve().parents[1] / ".cache" / "jax-tests"
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(CACHE_DIR))

import jax  # noqa: E402

jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
# Cache every compiled program: the suite is dominated by compile time, not run time.
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
