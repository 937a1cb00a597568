"""The calibrator's view of its fleet: where each device is and when it was last seen, the open drift alerts (from the
compass, ``<prefix>/<device>/alert``), rollback of a device's calibration, and the one answer for the whole fleet on
``<prefix>/@fleet``. No zenoh sessions inside: the service feeds it and sends its answers.

``<prefix>/@fleet`` replies once: ``{v, t_ns, count, devices: [{device, state, calibration_id, method, quality:
{residual_rms_ut, residual_rms_pct, coverage, holdout_rms_ut}, created_ns, age_s, last_seen_ns, location:
[lat, lon, alt_m] | null, location_source: reported|fleet|default|null, notes, alerts: [alert map, ...]}, ...]}``,
devices sorted by id.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from magnet import wire
from magnet.bounded import Recent
from magnet.drift import Alert, AlertKind, alert_from_message
from magnet.drift.alerts import ALERT_LIMITS
from magnet.fleet import Places

if TYPE_CHECKING:  # the service imports this module
    from services.calibrator.core import Calibrator

log = logging.getLogger("magnet.calibrator")

#: devices remembered at most without --max-devices (beyond: the least recently seen forgotten)
MAX_SEEN = 10_000
#: a rollback without --to looks this far back in the history for the previous calibration
ROLLBACK_DEPTH = 1_000
QUALITY_FIGURES = ("residual_rms_ut", "residual_rms_pct", "coverage", "holdout_rms_ut")


class FleetBook:
    """Last seen (ns, wall clock of the calibrator), places and open alerts per device, for at most ``max_devices``
    devices each (``--max-devices``): beyond, the least recently seen are forgotten, counted in ``forgotten`` and
    logged the first time."""

    def __init__(self, places: Places | None = None, max_devices: int = MAX_SEEN) -> None:
        self.places = places if places is not None else Places(max_reported=max_devices)
        self.last_seen_ns: Recent[str, int] = Recent(max_devices)
        self.alerts: Recent[str, dict[AlertKind, Alert]] = Recent(max_devices)
        self.max_devices = max_devices
        self.drops = wire.DropCounter()

    @property
    def forgotten(self) -> int:
        """Entries (last seen, reported place, open alerts) forgotten for the ``max_devices`` bound."""
        return self.last_seen_ns.evicted + self.alerts.evicted + self.places.reported.evicted

    def _check_bound(self, before: int) -> None:
        if before == 0 and self.forgotten:
            log.warning(
                "more than %d devices in the fleet book: the least recently seen are forgotten (counted in status "
                "forgotten_devices; raise --max-devices if they are genuine)",
                self.max_devices,
            )

    def seen(self, device: str, location: Any, now_ns: int) -> None:
        before = self.forgotten
        self.last_seen_ns[device] = now_ns
        self.places.report(device, location)
        self._check_bound(before)

    def field_ut(self, device: str) -> float | None:
        """The WMM |B| (uT) at the device's reported or configured place; None when neither is known."""
        if device not in self.places.reported and self.places.fleet.get(device) is None:
            return None
        return self.places.earth(device).total_ut

    def on_alert(self, key_expr: str, payload: bytes, prefix: str) -> None:
        """An alert raised or cleared by a compass; malformed ones dropped and counted."""
        try:
            message = wire.unpack(payload, ALERT_LIMITS)
            device = wire.message_device(message)
            wire.check_key(prefix, key_expr, wire.Kind.ALERT, device)
            alert = alert_from_message(message)
        except wire.WireError as exc:
            self.drops.drop(exc, "alert", log)
            return
        except ValueError as exc:
            self.drops.drop(wire.WireError("bad-alert", str(exc)), "alert", log)
            return
        open_alerts = self.alerts.get(device)
        if alert.cleared:
            if open_alerts is not None:
                open_alerts.pop(alert.kind, None)
            return
        before = self.forgotten
        if open_alerts is None:
            open_alerts = self.alerts[device] = {}
        self.alerts.touch(device)
        open_alerts[alert.kind] = alert
        self._check_bound(before)

    def location_source(self, device: str) -> str | None:
        if device in self.places.reported:
            return "reported"
        entry = self.places.fleet.get(device)
        if entry is not None and entry.location is not None:
            return "fleet"
        return "default" if self.places.default is not None else None


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
        "v": wire.WIRE_VERSION,
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


def rollback(calibrator: Calibrator, device: str, to_id: str | None, by: str | None) -> dict[str, Any]:
    """Put an earlier calibration of ``device`` back in force (``to_id``, else the one before the current), recorded
    in the history as a change (action rollback, by, at_ns, from_id). The reply map of the calibrate queryable; a
    store that cannot be read or written (full disk, damaged file) is a refusal saying so, nothing changed."""
    try:
        ok, message, extra = _roll_back(calibrator, device, to_id, by)
    except OSError as exc:
        ok, message, extra = False, f"not rolled back, the calibration in force stays: {exc}", {}
        log.warning("rollback of %s refused: %s", device, exc)
    return {
        "ok": ok,
        "action": "rollback",
        "device": device,
        "state": calibrator.state(device).value,
        "message": message,
        "progress": calibrator.progress(device).to_dict(),
        **extra,
    }


def _roll_back(calibrator: Calibrator, device: str, to_id: str | None, by: str | None) -> tuple[bool, str, dict]:
    current = calibrator.in_force.get(device)
    history = calibrator.store.history(device, limit=ROLLBACK_DEPTH)
    if to_id:
        target = next((r for r in history if r.id == to_id), None)
        missing = f"no calibration {to_id} in the history of {device} (magnet get calibration {device} --history)"
    else:
        target = next((r for r in history if current is None or r.id != current.id), None)
        missing = f"no earlier calibration of {device} to roll back to"
    if target is None:
        return False, missing, {}
    if current is not None and target.id == current.id:
        return False, f"calibration {target.id} is already in force for {device}", {}
    if not calibrator.made_here(target):
        unsigned = (
            f"calibration {target.id} of {device} is not signed by this calibrator's key: it was not made by a "
            "calibrator you trust (or before the key), so it is not signed now; calibrate the device instead"
        )
        return False, unsigned, {}
    record = calibrator.commit(
        device, target.calibration, change={"action": "rollback", "by": by or "", "to_id": target.id}
    )
    message = (
        f"calibration {target.id} (made at {target.created_ns} ns, version {target.version}) back in force for "
        f"{device} as version {record.version}, replacing {current.id if current else 'none'}"
    )
    return True, message, {"calibration": record.to_record()}
