"""Offline data: DSRL-format HDF5 files, padded episodes, training windows, relabelling, buffer.

Pipeline: `load_dataset` (file -> padded `Dataset`) -> `relabel_pareto` (optional, appends
relabelled copies) -> `trajectory_weights` -> `sample_windows` (jit-able batches). Online:
`buffer_init` / `buffer_add` build an `EpisodeBuffer` that `sample_windows` samples the same way.
"""

from safecdt_jax.data.buffer import EpisodeBuffer, buffer_add, buffer_init, buffer_size
from safecdt_jax.data.dataset import (
    Attrs,
    Dataset,
    DatasetError,
    make_dataset,
    select_episodes,
)
from safecdt_jax.data.dsrl import KEYS, load_dataset, write_dataset
from safecdt_jax.data.relabel import (
    RelabelConfig,
    grid_filter,
    pareto_front,
    policy_mean_labels,
    relabel_pareto,
)
from safecdt_jax.data.summary import summarize_dataset
from safecdt_jax.data.windows import (
    Windows,
    costs_to_go,
    episode_costs,
    episode_returns,
    returns_to_go,
    sample_windows,
    suffix_sums,
    trajectory_weights,
)

__all__ = [
    "KEYS",
    "Attrs",
    "Dataset",
    "DatasetError",
    "EpisodeBuffer",
    "RelabelConfig",
    "Windows",
    "buffer_add",
    "buffer_init",
    "buffer_size",
    "costs_to_go",
    "episode_costs",
    "episode_returns",
    "grid_filter",
    "load_dataset",
    "make_dataset",
    "pareto_front",
    "policy_mean_labels",
    "relabel_pareto",
    "returns_to_go",
    "sample_windows",
    "select_episodes",
    "suffix_sums",
    "summarize_dataset",
    "trajectory_weights",
    "write_dataset",
]
