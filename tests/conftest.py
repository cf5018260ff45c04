"""Shared test setup: CPU only, and one persistent compilation cache for every test process."""

import os
from pathlib import Path

# Outside the checkout, so a fresh clone (CI's, or a second worktree) starts from the programs
# an earlier run compiled instead of compiling the whole suite again (about 3x the warm time):
# entries are keyed by the program, the JAX version and the flags, so a stale one is never
# loaded for another program. `$JAX_COMPILATION_CACHE_DIR` moves it (the keys hold the folder's
# path, through XLA's autotuning cache beside it, so a copied cache folder starts cold).
CACHE_DIR = (Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
             / "safecdt-jax-tests" / "xla")
os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(CACHE_DIR))

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
# Cache every compiled program: the suite is dominated by compile time, not run time.
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


def _atomic_cache_writes() -> None:
    """JAX (0.10) writes a persistent-cache entry in place, so a test process reading the entry
    another one is still writing can get half a file, and deserialising it aborts the process
    (seen once as an xdist worker's "Fatal Python error: Aborted" in the cache read). Write
    each entry to a temporary file and rename it into place instead. A private JAX API: if it
    moves, the tests run with JAX's own writes."""
    try:
        from jax._src import lru_cache
    except ImportError:
        return
    cache_cls = getattr(lru_cache, "LRUCache", None)
    suffix = getattr(lru_cache, "_CACHE_SUFFIX", None)
    if cache_cls is None or suffix is None or getattr(cache_cls, "_atomic_put", False):
        return
    original = cache_cls.put

    def put(self, key: str, value: bytes) -> None:
        if getattr(self, "eviction_enabled", True) or not key:
            return original(self, key, value)
        final = self.path / f"{key}{suffix}"
        if final.exists():
            return None
        tmp = self.path / f".{key}.{os.getpid()}.tmp"
        tmp.write_bytes(value)
        os.replace(tmp, final)
        return None

    cache_cls.put = put
    cache_cls._atomic_put = True


_atomic_cache_writes()


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """(data path, checkpoint path, folder): a 4-episode PointCircle1 data set of the committed
    experts (20 steps each) and a tiny CDT pretrained for 2 updates, built once for every test
    that only needs some valid checkpoint to evaluate or deploy."""
    from data_helpers import write_expert_episodes

    from safecdt_jax.pretrain import default_pretrain, pretrain

    tmp = tmp_path_factory.mktemp("tiny_run")
    data = write_expert_episodes(tmp / "PointCircle1.hdf5")
    cfg = default_pretrain("tiny", steps=2, chunk=2)
    ckpt = pretrain(data, tmp / "ckpt", preset="tiny", config=cfg, progress=False).path
    return data, ckpt, tmp


@pytest.fixture(autouse=True)
def _programs_not_stored():
    """Every test starts with traced programs not stored on disk: a CLI test turns storing on
    for its process (`enable_persistent_cache`), which must not carry into the next test."""
    from safecdt_jax import programs

    programs.enable(None)
    yield
    programs.enable(None)
