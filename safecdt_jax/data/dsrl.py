"""DSRL-format HDF5 files: write ours, read ours and real DSRL files into a padded `Dataset`.

On disk (docs/METHOD.md A.1): flat datasets, one row per transition, episodes contiguous and split
by `terminals | timeouts`. Our files add file attributes and an optional `episode_info` group of
per-episode arrays; DSRL readers ignore both.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import h5py
import numpy as np

from safecdt_jax.data.dataset import (
    Attrs,
    Dataset,
    DatasetError,
    encode_attr,
    episode_bounds,
    pad_flat,
    to_flat,
)
from safecdt_jax.io import atomic_path

KEYS = (
    "observations",
    "next_observations",
    "actions",
    "rewards",
    "costs",
    "terminals",
    "timeouts",
)
FLOAT_KEYS = KEYS[:5]
EPISODE_GROUP = "episode_info"


def _check_flat(arrays: Mapping[str, Any], where: str, obs_dim: int | None) -> dict:
    """Validate and normalise flat rows; raise one DatasetError naming `where` and the problem."""
    missing = [k for k in KEYS if k not in arrays]
    if missing:
        raise DatasetError(f"{where}: missing key(s) {', '.join(missing)}")
    out = {}
    for k in KEYS:
        a = np.asarray(arrays[k])
        # DSRL stores rewards/costs/flags as N or N x 1, and a 1-D action space may be N.
        if k in ("rewards", "costs", "terminals", "timeouts") and a.ndim == 2 and a.shape[1] == 1:
            a = a[:, 0]
        if k == "actions" and a.ndim == 1:
            a = a[:, None]
        want = 2 if k in ("observations", "next_observations", "actions") else 1
        if a.ndim != want:
            raise DatasetError(f"{where}: key {k} has shape {a.shape}, expected {want}-D rows")
        out[k] = a
    rows = {k: out[k].shape[0] for k in KEYS}
    if len(set(rows.values())) != 1:
        listed = ", ".join(f"{k}={n}" for k, n in rows.items())
        raise DatasetError(f"{where}: keys disagree in row count ({listed})")
    if rows["observations"] == 0:
        raise DatasetError(f"{where}: contains no transitions (0 rows)")
    if out["next_observations"].shape != out["observations"].shape:
        raise DatasetError(
            f"{where}: next_observations shape {out['next_observations'].shape} differs from "
            f"observations shape {out['observations'].shape}"
        )
    if obs_dim is not None and out["observations"].shape[1] != obs_dim:
        raise DatasetError(
            f"{where}: observation size {out['observations'].shape[1]} does not match "
            f"obs_dim={obs_dim}"
        )
    for k in FLOAT_KEYS:
        try:
            out[k] = out[k].astype(np.float32)
        except (TypeError, ValueError) as e:
            raise DatasetError(f"{where}: key {k} is not numeric ({e})") from e
        bad = ~np.isfinite(out[k])
        if bad.any():
            row = int(np.argwhere(bad)[0][0])
            raise DatasetError(
                f"{where}: key {k} has {int(bad.sum())} non-finite value(s) (first at row {row})"
            )
    for k in ("terminals", "timeouts"):
        out[k] = out[k].astype(bool)
    return out


def _flat_from_input(data, where: str) -> tuple[dict, dict, dict]:
    """Flat rows, per-episode info and attrs from a Dataset, a flat mapping or episode dicts."""
    if isinstance(data, Dataset):
        if np.any(np.asarray(data.return_offset) != 0) or np.any(np.asarray(data.cost_offset) != 0):
            raise DatasetError(
                f"{where}: this Dataset has relabelled returns/costs-to-go (non-zero offsets), "
                "which the DSRL format cannot store; write the data before relabelling"
            )
        try:
            return to_flat(data), dict(data.episode_info), dict(data.attrs)
        except DatasetError as e:
            raise DatasetError(f"{where}: {e}") from None
    if isinstance(data, Mapping):
        return dict(data), {}, {}
    if isinstance(data, Sequence) and not isinstance(data, str):
        if not data:
            raise DatasetError(f"{where}: no episodes given")
        flat: dict[str, list] = {k: [] for k in KEYS}
        for i, ep in enumerate(data):
            missing = [k for k in FLOAT_KEYS if k not in ep]
            if missing:
                raise DatasetError(f"{where}: episode {i} is missing key(s) {', '.join(missing)}")
            n = np.asarray(ep["rewards"]).reshape(-1).shape[0]
            for k in FLOAT_KEYS:
                flat[k].append(np.asarray(ep[k]))
            term = np.asarray(ep.get("terminals", np.zeros(n)), bool).reshape(-1)
            if "timeouts" in ep:
                tout = np.asarray(ep["timeouts"], bool).reshape(-1)
            else:
                # Without explicit flags an episode ended by its time limit.
                tout = np.zeros(n, bool)
                tout[-1:] = ~term[-1:]
            flat["terminals"].append(term)
            flat["timeouts"].append(tout)
        return {k: np.concatenate(v, axis=0) for k, v in flat.items()}, {}, {}
    raise DatasetError(f"{where}: cannot write data of type {type(data).__name__}")


def write_dataset(
    path: str | os.PathLike,
    data: Dataset | Mapping[str, Any] | Sequence[Mapping[str, Any]],
    attrs: Mapping[str, Any] | None = None,
    episode_info: Mapping[str, Any] | None = None,
    compression: str | None = "gzip",
) -> None:
    """Write a DSRL-format HDF5 file atomically (temporary file in the same folder, os.replace).

    `data` is a `Dataset`, a mapping of the 7 flat DSRL keys (one row per transition), or a list
    of per-episode mappings (observations, next_observations, actions, rewards, costs; optional
    per-step terminals/timeouts, else a timeout on the last step). `attrs` become file attributes
    (strings and numbers as is, dicts/lists as JSON strings); `episode_info` arrays (leading dim =
    number of episodes) go to the `episode_info` group. A Dataset's own attrs and episode_info are
    written too (the arguments win on clashes). Values are stored as float32, flags as bool.
    """
    where = f"write_dataset({os.fspath(path)})"
    flat, info, all_attrs = _flat_from_input(data, where)
    flat = _check_flat(flat, where, None)
    info.update(dict(episode_info or {}))
    all_attrs.update(dict(attrs or {}))
    n_episodes = episode_bounds(flat["terminals"], flat["timeouts"])[0].size
    for k, v in info.items():
        if np.shape(v)[:1] != (n_episodes,):
            raise DatasetError(
                f"{where}: episode_info[{k!r}] has shape {np.shape(v)}, expected a leading "
                f"dimension of {n_episodes} episodes"
            )
    with atomic_path(path, suffix=".hdf5") as tmp, h5py.File(tmp, "w") as f:
        for k in KEYS:
            big = flat[k].ndim == 2
            f.create_dataset(k, data=flat[k], compression=compression if big else None)
        if info:
            group = f.create_group(EPISODE_GROUP)
            for k, v in info.items():
                group.create_dataset(k, data=np.asarray(v))
        for k, v in all_attrs.items():
            f.attrs[k] = encode_attr(v)


def _read_file(path: str) -> tuple[dict, dict, dict]:
    """Raw arrays, episode_info arrays and attrs of an HDF5 file, with file-level errors wrapped."""
    if not os.path.exists(path):
        raise DatasetError(f"{path}: file not found")
    if os.path.isdir(path):
        raise DatasetError(f"{path}: is a directory, not an HDF5 file")
    try:
        is_hdf5 = h5py.is_hdf5(path)
    except OSError:
        is_hdf5 = False
    if not is_hdf5:
        raise DatasetError(f"{path}: not an HDF5 file")
    try:
        with h5py.File(path, "r") as f:
            arrays = {}
            for k in KEYS:
                if k in f:
                    if not isinstance(f[k], h5py.Dataset):
                        raise DatasetError(f"{path}: key {k} is a group, not an array")
                    arrays[k] = f[k][()]
            info = {}
            if EPISODE_GROUP in f and isinstance(f[EPISODE_GROUP], h5py.Group):
                group = f[EPISODE_GROUP]
                info = {k: v[()] for k, v in group.items() if isinstance(v, h5py.Dataset)}
            attrs = {k: f.attrs[k] for k in f.attrs}
    except DatasetError:
        raise
    except (OSError, KeyError, TypeError, ValueError) as e:
        raise DatasetError(f"{path}: could not read the HDF5 contents ({e})") from e
    return arrays, info, attrs


def load_dataset(
    path: str | os.PathLike, obs_dim: int | None = None, horizon: int | None = None
) -> Dataset:
    """Read a DSRL-format HDF5 file (ours or a real DSRL download) into padded episodes.

    Episodes are split at `terminals | timeouts`; trailing rows without either flag form one more
    episode. Arrays are `[n_episodes, T, ...]` with T = `horizon` if given, else the longest
    episode, zero past each episode's `lengths`. Raw units: rewards and costs per step, unscaled.
    Raises `DatasetError` (one message naming the file and the problem) for: file not found or not
    HDF5, a missing key, keys with different row counts, an observation size other than `obs_dim`,
    non-finite values, an episode longer than `horizon`, or malformed `episode_info`.
    """
    path = os.fspath(path)
    raw, info, attrs = _read_file(path)
    flat = _check_flat(raw, path, obs_dim)
    starts, lengths = episode_bounds(flat["terminals"], flat["timeouts"])
    longest = int(lengths.max())
    if horizon is None:
        horizon = longest
    elif longest > horizon:
        ep = int(np.argmax(lengths))
        raise DatasetError(
            f"{path}: episode {ep} has {longest} steps, longer than horizon={horizon}"
        )
    n = lengths.size
    for k, v in info.items():
        if v.shape[:1] != (n,):
            raise DatasetError(
                f"{path}: episode_info[{k!r}] has shape {v.shape}, expected {n} episodes first"
            )
    end_rows = starts + lengths - 1
    pad = lambda k: pad_flat(flat[k], starts, lengths, horizon)
    return Dataset(
        observations=pad("observations"),
        next_observations=pad("next_observations"),
        actions=pad("actions"),
        rewards=pad("rewards"),
        costs=pad("costs"),
        lengths=lengths.astype(np.int32),
        terminals=flat["terminals"][end_rows],
        timeouts=flat["timeouts"][end_rows],
        return_offset=np.zeros(n, np.float32),
        cost_offset=np.zeros(n, np.float32),
        episode_info=info,
        attrs=Attrs(attrs),
    )
