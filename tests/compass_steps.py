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
