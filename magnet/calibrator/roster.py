"""The roster of the devices a calibrator serves (``Roster``): where each device is (reported, from the fleet file, or
the default place) and when it was last seen, and the open drift alerts (from the compass,
``<prefix>/<device>/alert``). No zenoh sessions inside: the service feeds it. The answer for every device
(``<prefix>/@fleet``) is ``magnet.calibrator.roster_reply``.
"""

from __future__ import annotations

import logging

from magnet import wire
from magnet.bounded import Recent
from magnet.calibrator.settings import DEFAULT_MAX_DEVICES
from magnet.drift import Alert, AlertKind, alert_from_message
from magnet.drift.alerts import ALERT_LIMITS
from magnet.earth.location import Location
from magnet.fleet.places import Places

log = logging.getLogger("magnet.calibrator")


class Roster:
    """Last seen (ns, wall clock of the calibrator), places and open alerts per device, for at most ``max_devices``
    devices each (``--max-devices``): beyond, the least recently seen are forgotten, counted in ``forgotten`` and
    logged the first time."""

    def __init__(self, places: Places | None = None, max_devices: int = DEFAULT_MAX_DEVICES) -> None:
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
                "more than %d devices in the roster: the least recently seen are forgotten (counted in status "
                "forgotten_devices; raise --max-devices if they are genuine)",
                self.max_devices,
            )

    def knows(self, device: str) -> bool:
        """Whether ``device`` was seen (and not forgotten since) or is in the fleet file."""
        return device in self.last_seen_ns or device in self.places.fleet

    def devices(self) -> set[str]:
        """Every device it knows of: seen, in the fleet file, or with open alerts."""
        return set(self.last_seen_ns) | set(self.places.fleet) | {d for d, a in self.alerts.items() if a}

    def seen(self, device: str, location: Location | None, now_ns: int) -> None:
        before = self.forgotten
        self.last_seen_ns[device] = now_ns
        self.places.report(device, location)
        self._check_bound(before)

    def field_ut(self, device: str) -> float | None:
        """The WMM |B| (uT) at the device's reported or configured place; None when neither is known."""
        if device not in self.places.reported and self.places.fleet.get(device) is None:
            return None
        return self.places.earth(device).total_ut

    def dip_deg(self, device: str) -> float | None:
        """The WMM dip (deg) at the device's reported or configured place, else at the service's ``--location``;
        None when none is known."""
        if self.places.location(device) is None:
            return None
        return self.places.earth(device).inclination_deg

    def declination_deg(self, device: str) -> float | None:
        """The WMM declination (deg) at the device's reported or configured place, else at the service's
        ``--location``; None when none is known."""
        if self.places.location(device) is None:
            return None
        return self.places.earth(device).declination_deg

    def open_alerts(self, device: str) -> list[str]:
        """The kinds of the device's open drift alerts, sorted (what a refresh may resolve)."""
        return sorted(kind.value for kind in (self.alerts.get(device) or {}))

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
