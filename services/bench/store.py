"""``magnet bench store [--devices N] [--db FILE.sqlite3|postgresql://...]``: what a store of calibrations costs the
calibrator: commits per second (one ``append`` per device, each its own transaction, as the calibrator commits them)
and the latency of reading a device's record in force back (``latest``: p50, p99 over 1,000 devices) and of reading
every record in force (``all_latest``, as a calibrator taking over does), for N devices (default 10,000).

Without ``--db``, a SQLite file in a temporary directory; a PostgreSQL URL must name an empty database (the bench
writes N records into it and leaves them).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from magnet import wire
from magnet.model import Calibration, Quality
from services.calibrator.store import open_store
from services.common.stores import StoreLocation

QUERIES = 1000


def _record(device: str, version: int, offset_ut: np.ndarray) -> wire.DeviceCalibration:
    quality = Quality(residual_rms_ut=0.3, coverage=0.95)
    calibration = Calibration("ellipsoid", offset_ut, np.eye(3), field_strength=51.0, quality=quality, accepted=True)
    return wire.DeviceCalibration(device, time.time_ns(), calibration, version=version)


def measure(location: StoreLocation, devices: int) -> dict[str, float]:
    """commits_per_s, latest_p50_ms, latest_p99_ms, all_latest_s of ``devices`` devices at ``location``."""
    rng = np.random.default_rng(0)
    names = [f"dev-{i:05d}" for i in range(devices)]
    with open_store(location) as store:
        if store.count():
            raise ValueError(f"{location} already holds records: give the bench an empty store")
        started = time.perf_counter()
        for name in names:
            offset = rng.uniform(-40, 40, 3)
            store.append(name, lambda v, n=name, o=offset: _record(n, v, o), {"action": "auto", "by": "bench"})
        commits_s = time.perf_counter() - started
        times = []
        for name in rng.choice(names, size=min(QUERIES, devices), replace=False):
            t0 = time.perf_counter()
            store.latest(str(name))
            times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        in_force = store.all_latest()
        all_s = time.perf_counter() - t0
    if len(in_force) != devices:
        raise ValueError(f"{location}: {len(in_force)} records in force read back, {devices} stored")
    p50, p99 = np.percentile(np.array(times) * 1000, [50, 99])
    return {"commits_per_s": devices / commits_s, "latest_p50_ms": p50, "latest_p99_ms": p99, "all_latest_s": all_s}


def run_store_benchmark(devices: int = 10_000, db: StoreLocation | None = None) -> str:
    with tempfile.TemporaryDirectory() as tmp:
        location = db if db is not None else Path(tmp) / "bench.sqlite3"
        kind = "SQLite" if isinstance(location, Path) else "PostgreSQL"
        f = measure(location, devices)
    return (
        f"store {kind} {location if db is not None else '(temporary file)'}, {devices} devices: "
        f"{f['commits_per_s']:.0f} commits/s (one append each, its own transaction); latest p50 "
        f"{f['latest_p50_ms']:.2f} ms, p99 {f['latest_p99_ms']:.2f} ms; all_latest {f['all_latest_s']:.2f} s"
    )
