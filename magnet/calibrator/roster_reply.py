"""The one answer for every device a calibrator serves, on ``<prefix>/@fleet`` (``roster_reply``), from its records in
force, collections and roster (``magnet.calibrator.roster``).

``<prefix>/@fleet`` replies once: ``{v, t_ns, count, devices: [{device, state, calibration_id, method, quality:
{residual_rms_ut, residual_rms_pct, coverage, holdout_rms_ut}, created_ns, age_s, last_seen_ns, location:
[lat, lon, alt_m] | null, location_source: reported|fleet|default|null, notes, alerts: [alert map, ...]}, ...]}``,
devices sorted by id.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

from magnet import wire
from magnet.calibrator.roster import Roster
from magnet.calibrator.status import State

QUALITY_FIGURES = ("residual_rms_ut", "residual_rms_pct", "coverage", "holdout_rms_ut")


def roster_reply(
    in_force: Mapping[str, wire.DeviceCalibration],
    collecting: Iterable[str],
    roster: Roster,
    state: Callable[[str], State],
    now_ns: int,
) -> dict[str, Any]:
    """The ``<prefix>/@fleet`` answer (see the module docstring): the devices with a record ``in_force``, those
    ``collecting`` and those the ``roster`` knows; ``state(device)`` says where each stands."""
    devices = sorted(set(in_force) | set(collecting) | roster.devices())
    return {
        "v": wire.RECORD_VERSION,
        "t_ns": now_ns,
        "count": len(devices),
        "devices": [_device_entry(in_force.get(device), roster, device, state(device), now_ns) for device in devices],
    }


def _device_entry(
    record: wire.DeviceCalibration | None, roster: Roster, device: str, state: State, now_ns: int
) -> dict[str, Any]:
    location = roster.places.location(device)
    entry: dict[str, Any] = {
        "device": device,
        "state": state.value,
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
        last_seen_ns=roster.last_seen_ns.get(device),
        location=None if location is None else location.to_wire(),
        location_source=roster.location_source(device) if location is not None else None,
        notes=roster.places.notes(device),
        alerts=[alert.to_message() for alert in roster.alerts.get(device, {}).values()],
    )
    return entry
