"""The compass's core as the tests drive it: built from a few settings, stepped on raw batches, its output cut back
into one ``wire.HeadingBatch`` per raw batch (float64, as computed; the wire's float32 is the encoder's business).

Import from a test module as ``from compass_steps import compass_core, heading_batches`` (pytest puts ``tests/`` on
``sys.path``).
"""

from __future__ import annotations

import numpy as np

from magnet import signing, wire
from magnet.compass import CompassCore, CoreSettings, HeadingColumns
from magnet.compass.core import DEFAULT_MAX_DEVICES
from magnet.drift import DEFAULT_DRIFT, DriftSettings
from magnet.earth.expected import Earth
from magnet.fleet.places import Places
from magnet.shard import EVERY_DEVICE, Shard

#: the wall clock the tests step at: 2026-06-01 (within the World Magnetic Model's life)
NOW_NS = 1_780_272_000_000_000_000
#: the simulator's date, 2026-01-01 UTC: the wall clock of ``heading_errors_deg``
WALL_NS = 1_767_225_600_000_000_000


def compass_core(
    earth: Earth | None = None,
    window: int = 1,
    trusted: signing.TrustedKeys | None = None,
    *,
    places: Places | None = None,
    max_devices: int = DEFAULT_MAX_DEVICES,
    shard: Shard = EVERY_DEVICE,
    drift: DriftSettings | None = DEFAULT_DRIFT,
) -> CompassCore:
    """A core that expects ``earth`` wherever a device has no place of its own (or ``places``)."""
    if places is None:
        places = Places(default_earth=earth, max_reported=max_devices)
    return CompassCore(CoreSettings(window, max_devices, shard, drift), places, trusted)


def heading_batches(core: CompassCore, batches: list[wire.RawBatch], now_ns: int = NOW_NS) -> list[wire.HeadingBatch]:
    """One heading batch per raw batch: ``core.step`` on them all at once, cut per batch."""
    if not batches:
        return []
    columns = wire.RawColumns.from_batches(batches)
    return cut(columns, core.step(columns, now_ns))


def cut(columns: wire.RawColumns, out: HeadingColumns) -> list[wire.HeadingBatch]:
    """``out`` (the step's output for ``columns``) as one ``wire.HeadingBatch`` per batch."""
    h, quat, bounds = out.headings, out.quat_wxyz, columns.bounds
    return [
        wire.HeadingBatch(
            device,
            seq,
            columns.t_ns[lo:hi],
            h.heading_deg[lo:hi],
            out.true_heading_deg[lo:hi],
            h.pitch_deg[lo:hi],
            h.roll_deg[lo:hi],
            h.field_ut[lo:hi],
            declination,
            cal_id,
            h.flags[lo:hi],
            quat[lo:hi] if quat is not None and np.isfinite(quat[lo:hi]).all() else None,
        )
        for device, seq, cal_id, declination, lo, hi in zip(
            columns.devices, columns.seqs, out.calibration_ids, out.declinations, bounds[:-1], bounds[1:]
        )
    ]


def heading_errors_deg(run, records: list[tuple[float, bytes]], batch: int = 25) -> np.ndarray:
    """The compass's heading error (deg, (N,), NaN where not fused) on a simulated ``run`` (t_s, mag_ut, acc_ms2,
    gyr_rads, quat_wxyz) sent as batches of ``batch`` samples of device "phone" at the place of the simulator's
    default, each record (encoded calibration message) put in force at its time (s)."""
    from magnet.earth.location import Location
    from services.bench import field_runs

    compass = CompassCore(
        CoreSettings(drift=None, sigmas=False), Places(default=Location.parse("50.45,30.52"), date="2026-01-01")
    )
    raw_key, cal_key = wire.key("magnet", "phone", wire.Kind.RAW), wire.key("magnet", "phone", wire.Kind.CALIBRATION)
    quat = np.full((len(run.t_s), 4), np.nan)
    pending = list(records)
    for seq, start in enumerate(range(0, len(run.t_s), batch)):
        part = slice(start, start + batch)
        while pending and pending[0][0] <= run.t_s[start]:
            assert compass.accept_calibration(pending.pop(0)[1], cal_key, "magnet")
        t_ns = WALL_NS + np.round(run.t_s[part] * 1e9).astype(np.int64)
        raw = wire.RawBatch("phone", seq, "sim", t_ns, run.mag_ut[part], run.acc_ms2[part], gyr_rads=run.gyr_rads[part])
        out = compass.step(compass.decode([(raw_key, wire.encode_raw(raw))], "magnet"), int(t_ns[-1]))
        quat[part] = out.quat_wxyz
    return field_runs.heading_error_deg(quat, run.quat_wxyz)
