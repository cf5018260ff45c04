"""Where cached artefacts (datasets, checkpoints) live on disk.

`SAFECDT_CACHE` overrides the root; the default is `~/.cache/safecdt-jax`. Every command that
writes into the cache also takes an explicit `--out`, which wins over both.
"""

from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "SAFECDT_CACHE"


def cache_root() -> Path:
    """The cache root folder: `$SAFECDT_CACHE` if set, else `~/.cache/safecdt-jax`."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "safecdt-jax"


# The default action recording of expert data (`experts.collect.ACTION_RECORDINGS`): the
# experts' Gaussian samples clipped to [-1, 1], DSRL's convention (docs/EXPERTS.md "Actions").
DEFAULT_ACTIONS = "sampled"


def dataset_path(task: str, actions: str = DEFAULT_ACTIONS) -> Path:
    """Default location of the collected source dataset for `task` (a DSRL-format HDF5 file):
    `TASK.hdf5` for the default action recording (`DEFAULT_ACTIONS`), `TASK-{actions}.hdf5`
    for expert data of another."""
    suffix = "" if actions == DEFAULT_ACTIONS else f"-{actions}"
    return cache_root() / "datasets" / f"{task}{suffix}.hdf5"


def checkpoint_dir(task: str, preset: str) -> Path:
    """Default folder of the pretrained CDT checkpoint for `task` with model preset `preset`."""
    return cache_root() / "checkpoints" / f"{task}-{preset}"
