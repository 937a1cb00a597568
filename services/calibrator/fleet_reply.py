"""The one answer for the whole fleet on ``<prefix>/@fleet`` (``fleet_reply``), from the calibrator's records in
force, collections and fleet book (``services.calibrator.fleet``).

``<prefix>/@fleet`` replies once: ``{v, t_ns, count, devices: [{device, state, calibration_id, method, quality:
{residual_rms_ut, residual_rms_pct, coverage, holdout_rms_ut}, created_ns, age_s, last_seen_ns, location:
[lat, lon, alt_m] | null, location_source: reported|fleet|default|null, notes, alerts: [alert map, ...]}, ...]}``,
devices sorted by id.
"""

from __future__ import annotations

from typing import Any

from magnet import wire
from services.calibrator.core import Calibrator
from services.calibrator.fleet import FleetBook

QUALITY_FIGURES = ("residual_rms_ut", "residual_rms_pct", "coverage", "holdout_rms_ut")


def fleet_reply(calibrator: Calibrator, now_ns: int) -> dict[str, Any]:
    """The ``<prefix>/@fleet`` answer (see the module docstring)."""
    book: FleetBook = calibrator.fleet
    devices = sorted(
        set(calibrator.in_force)
        | set(calibrator.collections)
        | set(book.last_seen_ns)
        | set(book.places.fleet)
        | {d for d, a in book.alerts.items() if a}
    )
    return {
        "v": wire.RECORD_VERSION,
        "t_ns": now_ns,
        "count": len(devices),
        "devices": [_device_entry(calibrator, book, device, now_ns) for device in devices],
    }


def _device_entry(calibrator: Calibrator, book: FleetBook, device: str, now_ns: int) -> dict[str, Any]:
    record = calibrator.in_force.get(device)
    location = book.places.location(device)
    entry: dict[str, Any] = {
        "device": device,
        "state": calibrator.state(device).value,
        "calibration_id": None,
        "method": None,
        "quality": None,
        "created_ns": None,
        "age_s": None,
    }
    if record is not None:
        quality = record.calibration.quality
        entry.update(
            calibration_id=record.id,
            method=record.calibration.method,
            quality={name: quality.get(name) for name in QUALITY_FIGURES},
            created_ns=record.created_ns,
            age_s=round((now_ns - record.created_ns) / 1e9, 3),
        )
    entry.update(
        last_seen_ns=book.last_seen_ns.get(device),
        location=None if location is None else location.to_wire(),
        location_source=book.location_source(device) if location is not None else None,
        notes=book.places.notes(device),
        alerts=[alert.to_message() for alert in book.alerts.get(device, {}).values()],
    )
    return entry
