"""Training and deployment curves as TensorBoard event files, beside the PNGs and JSON.

Everything is written on the host after the compiled work it describes (a pretraining chunk, a
round of expert training, a finished deployment), never from inside a jitted program, so the
curves cost nothing in the hot path and cannot change a result. View them with
`tensorboard --logdir FOLDER` (TensorBoard itself is not a dependency; the event files are
written with tensorboardX).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np


def write_scalars(folder: str | os.PathLike, series: Mapping[str, Sequence[float]],
                  steps: Sequence[int] | None = None, start: int = 0) -> Path:
    """Append scalar curves to the event files in `folder`: `series[tag][i]` at step
    `steps[i]` (default `start + i`), for the entries from index `start` on, so that a run can
    call it again with its growing history and write each point once. Returns the folder."""
    from tensorboardX import SummaryWriter

    folder = Path(folder)
    lengths = {len(v) for v in series.values()}
    if len(lengths) > 1:
        raise ValueError(f"curves of one call must have one length, got {sorted(lengths)}")
    n = lengths.pop() if lengths else 0
    steps = list(range(n)) if steps is None else [int(s) for s in steps]
    if len(steps) != n:
        raise ValueError(f"{len(steps)} steps for curves of length {n}")
    if start >= n:
        return folder
    # Event files are named by the second they are opened in: a second call within it would
    # overwrite the first's file without a suffix of its own.
    suffix = f".{time.time_ns()}"
    with SummaryWriter(logdir=os.fspath(folder), flush_secs=10, filename_suffix=suffix) as writer:
        for tag, values in series.items():
            values = np.asarray(values, np.float64)
            for i in range(start, n):
                if np.isfinite(values[i]):
                    writer.add_scalar(tag, float(values[i]), steps[i])
    return folder


def run_folder(label: str) -> str:
    """A run label (`safe_cdt B=30`, `limit 5 seed 0`) as a folder name TensorBoard lists."""
    return "".join(c if c.isalnum() or c in "._=-" else "_" for c in label)


def deployment_curves(folder: str | os.PathLike, runs: Mapping[str, Mapping[str, Sequence]]
                      ) -> list[Path]:
    """One event folder per deployment run (`folder/<label>`): per episode, the mean over seeds
    of the return, cost, violation rate (%), the cost and return targets, the replay lambda and
    the LoRA loss (`runs[label]` holds [seeds, episodes] metrics as results.json names them).
    `folder` is replaced, so a rerun into it leaves only its own curves."""
    names = {"return": "deploy/return", "cost": "deploy/cost", "violation": "deploy/vr_percent",
             "ctg_target": "deploy/ctg_target", "rtg_target": "deploy/rtg_target",
             "lambda": "deploy/lambda", "lora_loss": "deploy/lora_loss"}
    import shutil

    shutil.rmtree(folder, ignore_errors=True)  # a rerun into the same folder replaces the curves
    written = []
    for label, metrics in runs.items():
        series = {}
        for key, tag in names.items():
            if key in metrics:
                mean = np.asarray(metrics[key], np.float64).mean(axis=0)
                series[tag] = 100 * mean if key == "violation" else mean
        written.append(write_scalars(Path(folder) / run_folder(label), series,
                                     steps=range(1, len(next(iter(series.values()))) + 1)))
    return written
