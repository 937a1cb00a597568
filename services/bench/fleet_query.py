"""``magnet bench fleet [--devices N]``: how long ``magnet get fleet`` (the ``<prefix>/@fleet`` queryable) takes to
answer for N devices (default 1,000), each with a stored calibration and a place (a fleet file).

A store is filled directly, a calibrator process serves it on 127.0.0.1 (no multicast), and this process asks the
fleet query several times through its own Zenoh session; it prints the reply's size and the fastest and median times.
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from magnet import wire
from magnet.model import Calibration, Quality
from services.calibrator.store import CalibrationStore
from services.common.zenoh_session import free_ports

TARGET_S = 1.0


def fill_store(path: Path, devices: int, created_ns: int | None = None) -> list[str]:
    """``devices`` devices ``dev-0000``... each with one plausible calibration, in one transaction; their ids."""
    created = time.time_ns() if created_ns is None else created_ns
    rng = np.random.default_rng(0)
    names = [f"dev-{i:04d}" for i in range(devices)]
    with CalibrationStore(path) as store:
        store._db.execute("BEGIN")  # one transaction: the bench measures queries, not a thousand fsyncs
        for name in names:
            matrix = np.eye(3) + rng.uniform(-0.05, 0.05, (3, 3))
            cal = Calibration(
                "ellipsoid",
                rng.uniform(-40, 40, 3),
                (matrix + matrix.T) / 2,
                field_strength=51.0,
                sample_count=1500,
                quality=Quality(residual_rms_ut=0.3, residual_rms_pct=0.6, coverage=0.95, holdout_rms_ut=0.35),
                accepted=True,
                reason="accepted",
            )
            record = wire.DeviceCalibration(name, created, cal)
            store._db.execute(
                "INSERT INTO calibrations (device, id, created_ns, record) VALUES (?, ?, ?, ?)",
                (name, record.id, created, json.dumps(record.to_record(), sort_keys=True)),
            )
        store._db.execute("COMMIT")
    return names


def fleet_file(path: Path, names: list[str]) -> Path:
    """A fleet file placing every device somewhere on a grid of the world."""
    entries = {
        name: {"location": f"{-60 + (i * 7) % 120},{-180 + (i * 13) % 360},{i % 500}", "notes": f"unit {i}"}
        for i, name in enumerate(names)
    }
    path.write_text(json.dumps(entries))
    return path


def session_config(port: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def ask_fleet(
    session: zenoh.Session, prefix: str = "magnet", timeout_s: float = 10.0
) -> tuple[float, dict[str, Any] | None]:
    """(seconds, the decoded reply or None) of one fleet query."""
    start = time.perf_counter()
    for reply in session.get(f"{prefix}/@fleet", timeout=timeout_s):
        if reply.ok is not None:
            return time.perf_counter() - start, wire.unpack(reply.ok.payload.to_bytes())
    return time.perf_counter() - start, None


def wait_for_fleet(session: zenoh.Session, devices: int, timeout_s: float = 60.0) -> dict[str, Any]:
    """The first fleet reply that lists ``devices`` devices (the calibrator is up); RuntimeError after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        _, reply = ask_fleet(session, timeout_s=2.0)
        if reply is not None and reply.get("count", 0) >= devices:
            return reply
        time.sleep(0.2)
    raise RuntimeError(f"no fleet reply listing {devices} devices within {timeout_s} s")


def run_fleet_benchmark(devices: int = 1000, repeats: int = 10) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "fleet.db"
        names = fill_store(db, devices)
        port = free_ports(1)[0]
        command = [
            sys.executable,
            "-m",
            "services.cli",
            "calibrator",
            "--db",
            str(db),
            "--fleet",
            str(fleet_file(Path(tmp) / "fleet.json5", names)),
            "--no-multicast-scouting",
            "--listen",
            f"tcp/127.0.0.1:{port}",
        ]
        with open(Path(tmp) / "calibrator.log", "w") as log:
            proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
            try:
                with zenoh.open(session_config(port)) as session:
                    reply = wait_for_fleet(session, devices)
                    size = len(wire.pack(reply))
                    times = [ask_fleet(session)[0] for _ in range(repeats)]
            finally:
                proc.terminate()
                proc.wait(timeout=10)
    fastest, median = min(times), statistics.median(times)
    verdict = "meets" if median < TARGET_S else "MISSES"
    return (
        f"fleet query over {devices} devices: reply {size / 1024:.0f} KiB, fastest {fastest * 1000:.0f} ms, "
        f"median {median * 1000:.0f} ms of {repeats} ({verdict} the {TARGET_S:g} s target)"
    )
