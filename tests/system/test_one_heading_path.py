"""One heading path: the same recording through the live ``magnet compass`` (fed by ``magnet edge --replay`` on
loopback), through ``magnet heading`` and through ``CompassCore.step`` directly gives identical headings.

The recording is a simulator run with a gyroscope (the filter's path), its sensor values rounded to float32 once
and written exactly (``%.17g``): the raw wire carries float32, so all three see the very same numbers (the live
compass after the wire, the other two from the file). Compared:
- ``magnet heading`` with the step: its printed CSV (``%.4f``), character for character, against the step's float64
  values printed the same way (an in-process command run, no process: a unit test);
- the live compass with the step: every field of each heading message bit for bit against the step's output
  through the same encoder (float32 on the wire).
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh
from helpers import MAGNET, REPO_ROOT, connect_args, free_ports, listen_args, wait_for_liveliness

from magnet import wire
from magnet.attitude.heading import HeadingFlag
from magnet.compass import CompassCore, CoreSettings
from magnet.earth.location import Location
from magnet.fleet.places import Places
from magnet.simulator import SimulatorConfig, Trajectory, simulate
from services import cli

LOCATION, DATE = "50.45,30.52", "2026-06-01"
RATE_HZ, COUNT, BATCH = 100.0, 1500, 25
ANCHOR_NS = 1_780_272_000_000_000_000
COMPARED = ("heading_deg", "true_heading_deg", "pitch_deg", "roll_deg", "field_ut", "flags", "quat_wxyz")


def recording(path: Path) -> Path:
    """A moving simulator run with gyroscope as a CSV whose values are float32 numbers written exactly."""
    run = simulate(SimulatorConfig(trajectory=Trajectory.FIGURE8, rate_hz=RATE_HZ, count=COUNT, seed=4))
    t_s = np.arange(COUNT) / RATE_HZ
    values = [np.asarray(a, dtype=np.float32).astype(np.float64) for a in (run.mag_ut, run.acc_ms2, run.gyr_rads)]
    np.savetxt(
        path,
        np.hstack([t_s[:, None], *values]),
        delimiter=",",
        header="t_s,mx,my,mz,ax,ay,az,gx,gy,gz",
        comments="",
        fmt="%.17g",
    )
    return path


def stepped(csv: Path) -> tuple[wire.RawColumns, list]:
    """The step on the file's samples in batches of BATCH (as the edge cuts them), in drains of a few batches (as
    the live loop takes them): the raw columns and the step's output per drain."""
    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    t_ns = ANCHOR_NS + np.round((data[:, 0] - data[0, 0]) * 1e9).astype(np.int64)
    batches = [
        wire.RawBatch(
            "rec-1",
            k,
            "replay",
            t_ns[lo : lo + BATCH],
            data[lo : lo + BATCH, 1:4],
            data[lo : lo + BATCH, 4:7],
            gyr_rads=data[lo : lo + BATCH, 7:10],
        )
        for k, lo in enumerate(range(0, len(data), BATCH))
    ]
    core = CompassCore(CoreSettings(), Places(default=Location.parse(LOCATION), date=DATE))
    drains = []
    for start in range(0, len(batches), 5):
        columns = wire.RawColumns.from_batches(batches[start : start + 5])
        drains.append((columns, core.step(columns, ANCHOR_NS)))
    return batches, drains


def test_magnet_heading_prints_what_the_compass_step_gives(tmp_path, capsys):
    csv = recording(tmp_path / "rec.csv")
    _, drains = stepped(csv)
    assert cli.main(["heading", str(csv), "--location", LOCATION, "--date", DATE]) == 0
    rows = [line.split(",") for line in capsys.readouterr().out.splitlines()]
    header, rows = rows[0], rows[1:]
    assert len(rows) == COUNT
    step = {
        "heading_deg": np.concatenate([out.headings.heading_deg for _, out in drains]),
        "true_heading_deg": np.concatenate([out.true_heading_deg for _, out in drains]),
        "pitch_deg": np.concatenate([out.headings.pitch_deg for _, out in drains]),
        "roll_deg": np.concatenate([out.headings.roll_deg for _, out in drains]),
        "field_x_ut": np.concatenate([out.headings.field_ut[:, 0] for _, out in drains]),
    }
    flags = np.concatenate([out.headings.flags for _, out in drains])
    assert np.all(flags & HeadingFlag.FUSED), "the filter's path, not the tilt one"
    for name, values in step.items():
        column = header.index(name)
        assert [row[column] for row in rows] == [f"{v:.4f}" for v in values], name
    assert [int(row[header.index("flags")]) for row in rows] == flags.tolist()


def _decoded_step(drains: list) -> dict[int, wire.HeadingBatch]:
    """The step's output through the compass's own encoder, decoded: what the live compass would put, by seq."""
    out = {}
    for columns, headings in drains:
        for payload in CompassCore.encode(columns, headings):
            batch = wire.decode_heading(payload)
            out[batch.seq] = batch
    return out


@pytest.mark.integration
def test_the_live_compass_publishes_what_the_compass_step_gives(procs, tmp_path):
    csv = recording(tmp_path / "rec.csv")
    batches, drains = stepped(csv)
    expected = _decoded_step(drains)
    port = free_ports(1)[0]
    procs.start("compass", "compass", "--location", LOCATION, "--date", DATE, *listen_args(port))
    wait_for_liveliness(port, {"magnet/@alive/compass/compass"}, timeout_s=30)
    received: dict[int, wire.HeadingBatch] = {}
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        batch = wire.decode_heading(sample.payload.to_bytes())
        with lock:
            received[batch.seq] = batch

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session, session.declare_subscriber(wire.key("magnet", "*", wire.Kind.HEADING), on_sample):
        edge = [*MAGNET, "edge", "--replay", str(csv), "--device", "rec-1", "--speed", "20", "--batch", str(BATCH)]
        edge += [*listen_args(free_ports(1)[0]), *connect_args(port)]
        done = subprocess.run(edge, capture_output=True, text=True, timeout=120, cwd=REPO_ROOT)
        assert done.returncode == 0, done.stderr
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(received) < len(batches):
            time.sleep(0.1)
    with lock:
        live = dict(received)
    # the compass puts headings without blocking: a few may not reach this subscriber on a busy machine, but the
    # compass itself saw every batch from the first (its filter state), and each heading that arrives must be exact
    assert 0 in live and len(live) >= 0.8 * len(batches), f"{len(live)} of {len(batches)} heading messages"
    for seq, batch in live.items():
        for name in COMPARED:
            with contextlib.suppress(AttributeError):
                np.testing.assert_array_equal(
                    getattr(batch, name), getattr(expected[seq], name), err_msg=f"{seq} {name}"
                )
        assert batch.declination_deg == expected[seq].declination_deg
    assert np.all(np.concatenate([b.flags for b in live.values()]) & HeadingFlag.FUSED)


def test_a_file_is_one_devices_batches_cut_where_its_time_stops_going_forward():
    from services.commands.heading import sample_runs

    ms = 1_000_000
    # 10 ms steps, one stamp repeated (the time stops going forward), then a pause of about 2 s (beyond the gap)
    t_ns = np.array([0, 10, 20, 20, 30, 40, 2000, 2010], dtype=np.int64) * ms
    assert sample_runs(t_ns).tolist() == [3, 3, 2]
    assert sample_runs(np.arange(5, dtype=np.int64) * 10_000_000).tolist() == [5]
