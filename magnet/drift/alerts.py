"""Drift alerts: what drifted (``AlertKind``), the advice, the ``Alert`` event and its one entry from the wire."""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any

from magnet.wire.codec import Limits


class AlertKind(enum.Enum):
    """What drifted (the alert message's ``kind``)."""

    FIELD_STRENGTH = "field_strength"
    DIP = "dip"
    CALIBRATION_AGE = "calibration_age"


ADVICE = {
    AlertKind.FIELD_STRENGTH: (
        "the calibrated field strength departs from {ref}: look for new iron or a motor near "
        "the sensor, a bent mount or a swapped part, then recalibrate"
    ),
    AlertKind.DIP: (
        "the calibrated dip angle departs from {ref}: look for new iron near the sensor or a moved "
        "mount (magnetometer turned against the accelerometer), then recalibrate"
    ),
    AlertKind.CALIBRATION_AGE: "the calibration is older than {ref}: recalibrate (magnet calibrate DEVICE start)",
}


#: the advice of a cleared alert (received ones; the compass that clears one says why in its own log)
CLEARED_ADVICE = "cleared: the departure ended, or a new calibration came into force"


def advice_for(kind: AlertKind, expected: float, cleared: bool = False) -> str:
    """The advice of an alert, from the fixed table ``ADVICE`` keyed by what drifted, with its expected value
    (uT, degrees or days): never taken from a message, so that a peer allowed to raise alerts cannot make an operator
    read its words."""
    if cleared:
        return CLEARED_ADVICE
    if kind is AlertKind.CALIBRATION_AGE:
        return ADVICE[kind].format(ref=f"{expected:g} days")
    unit = "uT" if kind is AlertKind.FIELD_STRENGTH else "deg"
    return ADVICE[kind].format(ref=f"{expected:.1f} {unit}")


@dataclasses.dataclass(frozen=True)
class Alert:
    """One alert event. ``since_ns``: when the departure (or, cleared, the recovery) began; measured and expected in
    uT (field_strength), degrees (dip) or days (calibration_age)."""

    device: str
    kind: AlertKind
    since_ns: int
    measured: float
    expected: float
    advice: str
    cleared: bool = False

    def to_message(self) -> dict[str, Any]:
        """The ``<prefix>/<device>/alert`` map: v, device, kind, since_ns, measured, expected, advice (+ cleared)."""
        out: dict[str, Any] = {
            "v": 1,
            "device": self.device,
            "kind": self.kind.value,
            "since_ns": int(self.since_ns),
            "measured": round(float(self.measured), 4),
            "expected": round(float(self.expected), 4),
            "advice": self.advice,
        }
        if self.cleared:
            out["cleared"] = True
        return out


MAX_ADVICE_CHARS = 1_000
#: what msgpack may build of one alert message (``magnet.wire.Limits``): a handful of fields, the advice text
ALERT_LIMITS = Limits(payload_bytes=16 * 1024, array=16, map=32, text=4 * MAX_ADVICE_CHARS, binary=0, items=256)


def alert_from_message(message: Any) -> Alert:
    """The one entry of an alert map from outside (``<prefix>/<device>/alert``): ValueError naming what is wrong.
    The device id is the caller's to check (``magnet.wire.message_device``). The message's ``advice`` is checked and
    then replaced by the table's (``advice_for``): the text shown is never the sender's."""
    if not isinstance(message, dict):
        raise ValueError("an alert must be a map")
    if message.get("v") != 1:
        raise ValueError(f"alert schema version {message.get('v')!r}, expected 1")
    try:
        kind = AlertKind(message.get("kind"))
    except ValueError:
        raise ValueError(f"alert kind must be one of {', '.join(k.value for k in AlertKind)}") from None
    since = message.get("since_ns")
    if isinstance(since, bool) or not isinstance(since, int) or since < 0:
        raise ValueError("alert since_ns must be a whole number of ns >= 0")
    numbers: list[Any] = [message.get("measured"), message.get("expected")]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in numbers):
        raise ValueError("alert measured and expected must be finite numbers")
    advice, cleared = message.get("advice"), message.get("cleared", False)
    if not isinstance(advice, str) or len(advice) > MAX_ADVICE_CHARS:
        raise ValueError(f"alert advice must be text of at most {MAX_ADVICE_CHARS} characters")
    if not isinstance(cleared, bool):
        raise ValueError("alert cleared must be true or false")
    measured, expected = float(numbers[0]), float(numbers[1])
    return Alert(
        str(message.get("device")), kind, since, measured, expected, advice_for(kind, expected, cleared), cleared
    )
