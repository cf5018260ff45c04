"""Small source data sets for tests, made the way real ones are: the committed expert snapshots."""

import functools
from pathlib import Path

import jax
import numpy as np

from safecdt_jax.data.collect import write_collected
from safecdt_jax.data.dataset import Dataset, select_episodes
from safecdt_jax.experts.collect import rollout_snapshots, snapshot_path


@functools.cache
def expert_episodes(task: str = "PointCircle1", n: int = 4, horizon: int = 20, seed: int = 0,
                    chunk: int = 100) -> Dataset:
    """The first `n` of one `horizon`-step episode per committed expert snapshot of `task`."""
    raw = rollout_snapshots(jax.random.PRNGKey(seed), snapshot_path(task), 1, horizon=horizon,
                            chunk=chunk)
    return select_episodes(raw, np.arange(n))


def write_expert_episodes(path, **kwargs) -> Path:
    """`expert_episodes(**kwargs)` written to `path` as DSRL-format HDF5; returns the path."""
    return write_collected(path, expert_episodes(**kwargs))
