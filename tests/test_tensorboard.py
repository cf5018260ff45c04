"""TensorBoard curves: the event files hold every point once, at its step, under its tag."""

import struct

import numpy as np

from safecdt_jax.tensorboard import deployment_curves, write_scalars


def read_scalars(folder):
    """{tag: [(step, value)]} from every event file in `folder` (TFRecord framing)."""
    from tensorboardX.proto.event_pb2 import Event

    out = {}
    for path in sorted(folder.glob("events.out.tfevents.*")):
        data = path.read_bytes()
        i = 0
        while i < len(data):
            (length,) = struct.unpack("<Q", data[i:i + 8])
            event = Event.FromString(data[i + 12:i + 12 + length])
            i += 12 + length + 4
            for value in event.summary.value:
                out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out


def test_write_scalars_appends_each_point_once(tmp_path):
    curves = {"pretrain/loss": [3.0, 2.0, 1.5], "pretrain/ll": [-1.0, -0.5, float("nan")]}
    write_scalars(tmp_path, {k: v[:2] for k, v in curves.items()}, [100, 200])
    write_scalars(tmp_path, curves, [100, 200, 300], start=2)  # the run went on: only the new
    got = read_scalars(tmp_path)
    assert got["pretrain/loss"] == [(100, 3.0), (200, 2.0), (300, 1.5)]
    assert got["pretrain/ll"] == [(100, -1.0), (200, -0.5)]  # NaN points are left out


def test_deployment_curves_per_run_means_over_seeds(tmp_path):
    metrics = {"cost": [[10.0, 31.0], [20.0, 0.0]], "violation": [[0.0, 1.0], [0.0, 0.0]]}
    deployment_curves(tmp_path / "tb", {"safe_cdt B=30": metrics})
    got = read_scalars(tmp_path / "tb" / "safe_cdt_B=30")
    assert got["deploy/cost"] == [(1, 15.0), (2, 15.5)]
    assert got["deploy/vr_percent"] == [(1, 0.0), (2, 50.0)]
    deployment_curves(tmp_path / "tb", {"zero_shot": metrics})  # a rerun replaces the curves
    assert sorted(p.name for p in (tmp_path / "tb").iterdir()) == ["zero_shot"]
    assert np.isclose(read_scalars(tmp_path / "tb" / "zero_shot")["deploy/cost"][1][1], 15.5)
