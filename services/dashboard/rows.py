"""One device as the dashboard's fleet table shows it (``DeviceRow``), and its drift alerts as the page gets them.

Units: angles in degrees, fields in uT, times ``*_ns`` (wall clock, ns) or ``*_s`` (monotonic seconds).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from magnet.attitude.heading import HeadingFlag
from magnet.drift import Alert
from magnet.earth.geomag import EarthField
from magnet.earth.location import Location

STALE_S = 5.0  # no heading for this long (and for SILENT_INTERVALS of the device's own interval): the row says so
SILENT_INTERVALS = 5  # a device whose headings stop for this many of its own intervals between batches is silent
FUSED_FLAG = int(HeadingFlag.FUSED)  # attitude from the gyroscope-aided filter


def finite_or_none(value: Any) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if np.isfinite(number) else None


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


@dataclasses.dataclass
class DeviceRow:
    """One device as the fleet table shows it."""

    device: str
    version: int = 0
    alive: bool | None = None
    sensor: str = ""
    state: str = "waiting"
    method: str | None = None
    session: bool = False
    samples: int | None = None
    coverage: float | None = None
    missing: tuple[str, ...] = ()
    reason: str = ""
    accepted: bool | None = None
    residual_ut: float | None = None
    calibration_id: str = ""
    calibrated_ns: int | None = None
    seq: int | None = None
    heading_deg: float | None = None
    true_heading_deg: float | None = None
    heading_sigma_deg: float | None = None  # one sigma of the last heading (deg), as the compass sent it
    pitch_deg: float | None = None
    roll_deg: float | None = None
    field_ut: float | None = None
    dip_deg: float | None = None
    flags: int = 0
    quat_wxyz: tuple[float, ...] | None = None
    declination_deg: float | None = None
    truth_error_deg: float | None = None
    heading_s: float | None = None
    interval_s: float | None = None  # the device's running interval between heading batches (monotonic s)
    location: Location | None = None  # where the device says it is (its raw batches), for the expected field
    t_ns: int | None = None
    drift: dict[str, Alert] = dataclasses.field(default_factory=dict)  # open drift alerts by kind

    def status(self) -> str:
        """What the state badge says: a calibrated device with an open drift alert is never plainly calibrated. A
        drift alert is only raised against a calibration in force, so one that arrives before the page has heard of
        that calibration (a dashboard started late, a busy machine) marks the device drifted too."""
        if self.session:
            return "session"
        if self.drift and self.state in ("calibrated", "waiting"):
            return "drifted"
        return self.state

    def silent(self, now_s: float) -> bool:
        """Whether the device's headings stopped: none for SILENT_INTERVALS of its own interval, and at least STALE_S
        (a vehicle that stops sending while its edge, and so its liveliness token, lives on)."""
        if self.heading_s is None:
            return False
        return now_s - self.heading_s > max(STALE_S, SILENT_INTERVALS * (self.interval_s or 0.0))

    def alerts(self, now_s: float, earth: EarthField | None) -> list[str]:
        """Short phrases for what needs a person's attention."""
        out = [f"drift: {kind.replace('_', ' ')}" for kind in sorted(self.drift)]
        if self.alive is False:
            out.append("offline")
        if self.silent(now_s):
            out.append("no headings")
        if self.state in ("collecting", "idle", "waiting") and self.heading_s is not None:
            out.append("not calibrated")
        if self.accepted is False and self.state in ("collecting", "session"):
            out.append("fit rejected")
        for flag, text in (
            (HeadingFlag.FIELD_DISTURBED, "field disturbed"),
            (HeadingFlag.DIP_DISTURBED, "dip disturbed"),
            (HeadingFlag.NO_TILT, "no tilt"),
        ):
            if self.flags & flag:
                out.append(text)
        if earth is not None and (earth.blackout or earth.caution):
            out.append("weak horizontal field")
        return out

    def to_json(self, now_s: float, earth: EarthField | None) -> dict[str, Any]:
        return {
            "device": self.device,
            "alive": False if self.alive and self.silent(now_s) else self.alive,
            "sensor": self.sensor,
            "state": self.state,
            "method": self.method,
            "session": self.session,
            "samples": self.samples,
            "coverage": _round(self.coverage, 3),
            "missing": list(self.missing),
            "reason": self.reason,
            "accepted": self.accepted,
            "residual_ut": _round(self.residual_ut, 3),
            "calibration_id": self.calibration_id,
            "calibrated_ms": None if self.calibrated_ns is None else self.calibrated_ns // 1_000_000,
            "seq": self.seq,
            "t_ms": None if self.t_ns is None else self.t_ns // 1_000_000,
            "heading_deg": _round(self.heading_deg, 2),
            "true_heading_deg": _round(self.true_heading_deg, 2),
            "heading_sigma_deg": _round(self.heading_sigma_deg, 2),
            "pitch_deg": _round(self.pitch_deg, 2),
            "roll_deg": _round(self.roll_deg, 2),
            "field_ut": _round(self.field_ut, 2),
            "dip_deg": _round(self.dip_deg, 2),
            "flags": self.flags,
            "quat_wxyz": None if self.quat_wxyz is None else [round(q, 5) for q in self.quat_wxyz],
            "declination_deg": _round(self.declination_deg, 2),
            "truth_error_deg": _round(self.truth_error_deg, 2),
            "fused": bool(self.flags & FUSED_FLAG),
            "alerts": self.alerts(now_s, earth),
            "status": self.status(),
            "drift": [drift_json(alert) for _, alert in sorted(self.drift.items())],
        }


DRIFT_UNITS = {"field_strength": "uT", "dip": "deg", "calibration_age": "days"}


def drift_json(alert: Alert) -> dict[str, Any]:
    """One open drift alert for the page: kind, since (ms, wall clock), measured and expected in ``unit``, advice."""
    return {
        "kind": alert.kind.value,
        "since_ms": alert.since_ns // 1_000_000,
        "measured": round(alert.measured, 2),
        "expected": round(alert.expected, 2),
        "unit": DRIFT_UNITS.get(alert.kind.value, ""),
        "advice": alert.advice,
    }
