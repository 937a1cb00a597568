"""Parameters onto a vehicle over MAVLink: ``apply_params(url, params)`` for ``magnet export --apply URL``.

The exchange (MAVLink's parameter protocol, docs/mavlink.md) is a transaction: wait for the autopilot's HEARTBEAT
(the first from a component that is not a camera, gimbal or ground station and whose autopilot field is not
MAV_AUTOPILOT_INVALID: its system and component id, and ``base_mode``); refuse while that component reports armed
(MAV_MODE_FLAG_SAFETY_ARMED), since a compass changing under a flying vehicle's estimator is a hazard; read every
parameter's value now (PARAM_REQUEST_READ -> PARAM_VALUE) before writing any; set each (PARAM_SET, as a 32-bit float)
and read the autopilot's answer (PARAM_VALUE of that name), retrying a few times, the armed flag checked again before
every write; after the last, its next HEARTBEAT must still say disarmed. A value not confirmed, another value
confirmed, arming partway or silence: every parameter written is set back to its old value and the error says which
were restored and which could not be. The report lists every parameter with its old and new value.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from pymavlink import mavutil

from magnet.autopilot import hwid

HEARTBEAT_TIMEOUT_S = 5.0
ANSWER_TIMEOUT_S = 1.0
ATTEMPTS = 3
MAX_NAME_CHARS = 16  # PARAM_SET.param_id is 16 characters
CONFIRM_HEARTBEAT_S = 3.0  # after the writes: the autopilot's next HEARTBEAT (1 Hz on ArduPilot and PX4) within this
#: HEARTBEAT types that are never the autopilot, whatever their autopilot field says
NOT_AUTOPILOT_TYPES = {
    getattr(mavutil.mavlink, f"MAV_TYPE_{kind}")
    for kind in ("GCS", "ONBOARD_CONTROLLER", "CAMERA", "GIMBAL", "ADSB", "ODID", "SERVO", "BATTERY", "LOG")
    if hasattr(mavutil.mavlink, f"MAV_TYPE_{kind}")
}


class ApplyError(ValueError):
    """The parameters could not be applied; the message says why and what to do."""


@dataclasses.dataclass(frozen=True)
class ParamChange:
    """One parameter: its value before (None: not read), the value asked for and the value the vehicle read back."""

    name: str
    old: float | None
    new: float
    read_back: float

    @property
    def changed(self) -> bool:
        return self.old is None or np.float32(self.old) != np.float32(self.new)


@dataclasses.dataclass(frozen=True)
class ApplyReport:
    """What ``apply_params`` did to vehicle ``sysid``/``compid``: one ``ParamChange`` per parameter, in order."""

    sysid: int
    compid: int
    changes: tuple[ParamChange, ...]

    def lines(self) -> list[str]:
        """One line per parameter: ``NAME: old -> new`` (or ``NAME: new (unchanged)``)."""
        out = []
        for c in self.changes:
            before = "?" if c.old is None else f"{c.old:g}"
            out.append(
                f"{c.name}: {before} -> {c.read_back:g}" if c.changed else f"{c.name}: {c.read_back:g} (unchanged)"
            )
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "sysid": self.sysid,
            "compid": self.compid,
            "changed": [dataclasses.asdict(c) for c in self.changes if c.changed],
            "unchanged": [c.name for c in self.changes if not c.changed],
        }


def _check(params: Mapping[str, float]) -> None:
    if not params:
        raise ApplyError("no parameters to apply")
    for name, value in params.items():
        if not name or len(name) > MAX_NAME_CHARS or not name.isascii():
            raise ApplyError(f"parameter name {name!r} is not 1..{MAX_NAME_CHARS} ASCII characters")
        if isinstance(value, bool) or not np.isfinite(float(value)):
            raise ApplyError(f"parameter {name} must be a finite number, got {value!r}")


class _Link:
    """One MAVLink connection to one vehicle's autopilot component (the first HEARTBEAT from an autopilot: not a
    camera, gimbal or ground station, its autopilot field not MAV_AUTOPILOT_INVALID), watching that component's armed
    flag only; parameters are asked of that system and component and their answers taken from it alone."""

    def __init__(self, url: str, baud: int, sysid: int | None) -> None:
        try:
            self.conn = mavutil.mavlink_connection(url, baud=baud, source_system=255, source_component=190)
        except Exception as exc:  # pymavlink raises what its transport raises (OSError, OverflowError, ...)
            raise ApplyError(f"{url}: cannot open it: {exc}") from None
        self.want = sysid
        self.sysid = self.compid = 0
        self.armed = False
        self.heartbeats = 0  # the autopilot's heartbeats seen so far
        self.other: float | None = None  # the last value read back that was not the one sent

    def close(self) -> None:
        self.conn.close()

    def _heartbeat(self, message: Any) -> None:
        if message.type in NOT_AUTOPILOT_TYPES or message.autopilot == mavutil.mavlink.MAV_AUTOPILOT_INVALID:
            return
        if self.want is not None and message.get_srcSystem() != self.want:
            return
        if not self.sysid:
            self.sysid, self.compid = message.get_srcSystem(), message.get_srcComponent()
        if (message.get_srcSystem(), message.get_srcComponent()) == (self.sysid, self.compid):
            self.armed = bool(message.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            self.heartbeats += 1

    def _from_autopilot(self, message: Any) -> bool:
        return (message.get_srcSystem(), message.get_srcComponent()) == (self.sysid, self.compid)

    def wait(self, kind: str, timeout_s: float, name: str | None = None) -> Any:
        """The next message of ``kind`` from the autopilot (PARAM_VALUE: of ``name``), or None after ``timeout_s``;
        heartbeats seen meanwhile update the armed flag."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            message = self.conn.recv_match(type=["HEARTBEAT", kind], blocking=True, timeout=left)
            if message is None:
                return None
            if message.get_type() == "HEARTBEAT":
                self._heartbeat(message)
                if kind == "HEARTBEAT" and self.sysid and self._from_autopilot(message):
                    return message
                continue
            if not self._from_autopilot(message):
                continue
            if name is None or message.param_id == name:
                return message
        return None

    def drain(self) -> None:
        """Take every message already received (heartbeats update the armed flag) without waiting."""
        while (message := self.conn.recv_match(type="HEARTBEAT", blocking=False)) is not None:
            self._heartbeat(message)

    def refuse_if_armed(self) -> None:
        if self.armed:
            raise ApplyError(
                f"vehicle {self.sysid} is armed: its compass parameters are not changed in flight; disarm it and "
                "apply again"
            )

    def read(self, name: str) -> float | None:
        answer = self.read_message(name)
        return None if answer is None else float(answer.param_value)

    def read_message(self, name: str) -> Any:
        """The autopilot's PARAM_VALUE of ``name`` (asked up to ``ATTEMPTS`` times), or None."""
        for _ in range(ATTEMPTS):
            self.conn.mav.param_request_read_send(self.sysid, self.compid, name.encode(), -1)
            answer = self.wait("PARAM_VALUE", ANSWER_TIMEOUT_S, name)
            if answer is not None:
                return answer
        return None

    def check_sensor(self, name: str, wanted: int) -> None:
        """The vehicle's id parameter ``name`` must name sensor ``wanted`` (the record's): ApplyError otherwise,
        before anything is written (the values would land on another compass)."""
        answer = self.read_message(name)
        if answer is None:
            raise ApplyError(f"vehicle {self.sysid} does not answer for {name}: which compass is this?")
        held = hwid.hardware_id(float(answer.param_value), int(answer.param_type))
        if held != wanted:
            kind = hwid.MAV_AUTOPILOT_PX4 if name.startswith("CAL_MAG") else hwid.MAV_AUTOPILOT_ARDUPILOTMEGA
            now = "no sensor id" if held is None else hwid.describe(held, kind)
            raise ApplyError(
                f"vehicle {self.sysid}'s {name} is {now}, but this calibration was fitted for "
                f"{hwid.describe(wanted, kind)}: the values would land on another compass (one missing at boot moves "
                "the others up); nothing written. Export the record of the compass that is there"
            )

    def set(self, name: str, value: float, *, while_disarmed: bool = True, attempts: int = ATTEMPTS) -> float | None:
        """Send ``name`` = ``value`` (as a 32-bit float) until the autopilot confirms it: the value confirmed, or
        None (no confirmation, or another value, after ``attempts`` tries; the last other value is in ``other``).
        ``while_disarmed``: the armed flag is checked (after taking what has arrived) before every try."""
        sent = np.float32(value)
        self.other = None
        for _ in range(attempts):
            if while_disarmed:
                self.drain()
                if self.armed:
                    raise _ArmedPartwayError(name)
            self.conn.mav.param_set_send(
                self.sysid, self.compid, name.encode(), float(sent), mavutil.mavlink.MAV_PARAM_TYPE_REAL32
            )
            answer = self.wait("PARAM_VALUE", ANSWER_TIMEOUT_S, name)
            if answer is not None and np.float32(answer.param_value) == sent:
                return float(answer.param_value)
            if answer is not None:
                self.other = float(answer.param_value)
        return None

    def restore(self, name: str, old: float) -> bool:
        """Set ``name`` back to ``old``, armed or not; True once the autopilot confirms it holds ``old`` (its answer
        to the PARAM_SET, or else to a PARAM_REQUEST_READ)."""
        if self.set(name, old, while_disarmed=False, attempts=1) is not None:
            return True
        now = self.read(name)
        return now is not None and np.float32(now) == np.float32(old)

    def disarmed_after(self, seen: int) -> bool | None:
        """After the writes: wait for the autopilot's next HEARTBEAT (counted past ``seen``); False if it says
        armed, None if none came within ``CONFIRM_HEARTBEAT_S``."""
        deadline = time.monotonic() + CONFIRM_HEARTBEAT_S
        while self.heartbeats <= seen and (left := deadline - time.monotonic()) > 0:
            self.wait("HEARTBEAT", left)
        if self.heartbeats <= seen:
            return None
        return not self.armed


class _ArmedPartwayError(Exception):
    """The autopilot reported armed before the write of ``name``."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.name = name


def _undo(link: _Link, old: Mapping[str, float], touched: list[str], why: str) -> ApplyError:
    """Restore every parameter in ``touched`` (newest first) to its ``old`` value; the error saying ``why``, which
    were restored and which could not be."""
    restored: list[str] = []
    lost: list[str] = []
    for name in reversed(touched):
        (restored if link.restore(name, old[name]) else lost).append(name)
    said = f"{why}; restored to their old values: {', '.join(reversed(restored)) or 'none'}"
    if lost:
        was = ", ".join(f"{n} (was {old[n]:g})" for n in reversed(lost))
        said += f"; NOT restored (check them on the vehicle): {was}"
    return ApplyError(said)


def apply_params(
    url: str,
    params: Mapping[str, float],
    *,
    baud: int = 57600,
    sysid: int | None = None,
    sensors: Mapping[str, int] | None = None,
) -> ApplyReport:
    """Set ``params`` (name -> value) on the vehicle at ``url`` (a pymavlink URL: udpin:HOST:PORT, udpout:..., tcp:...,
    or a serial device at ``baud``) as one transaction; ``sysid`` picks a vehicle (default: the first autopilot heard).

    Every parameter is read first (none written unless all answer); the autopilot component must report disarmed
    before and between writes and in its first HEARTBEAT after the last one; each write is confirmed by the value
    read back. On a value not confirmed, another value confirmed, arming partway or no HEARTBEAT after the writes,
    every parameter written so far (the failing one included) is set back to its old value and ApplyError (a
    ValueError) names the cause, the parameters restored and any that could not be. ApplyError too when no vehicle
    answers, it is armed at the start, or it has no such parameter (nothing written then). ``sensors``: id parameters
    (``COMPASS_DEV_IDn``, ``CAL_MAGn_ID``) -> the sensor the values were fitted for: read first, never written; one
    that names another sensor refuses the whole (nothing written)."""
    _check(params)
    link = _Link(url, baud, sysid)
    try:
        if link.wait("HEARTBEAT", HEARTBEAT_TIMEOUT_S) is None:
            raise ApplyError(f"{url}: no vehicle's HEARTBEAT within {HEARTBEAT_TIMEOUT_S:g} s")
        link.refuse_if_armed()
        for name, wanted in (sensors or {}).items():
            link.check_sensor(name, wanted)
        old: dict[str, float] = {}
        for name in params:
            value = link.read(name)
            if value is None:
                raise ApplyError(f"vehicle {link.sysid} does not answer for parameter {name}: is it its name?")
            old[name] = value
        return _write_all(link, params, old)
    finally:
        link.close()


def _write_all(link: _Link, params: Mapping[str, float], old: Mapping[str, float]) -> ApplyReport:
    touched: list[str] = []
    read_back: dict[str, float] = {}
    for name, value in params.items():
        try:
            touched.append(name)
            confirmed = link.set(name, value)
        except _ArmedPartwayError:
            touched.pop()
            raise _undo(link, old, touched, f"vehicle {link.sysid} armed partway, before {name}: stopped") from None
        if confirmed is None:
            got = "no PARAM_VALUE" if link.other is None else f"it read back {link.other:g}"
            sent = float(np.float32(value))
            why = f"vehicle {link.sysid} did not take {name} = {sent:g} after {ATTEMPTS} tries ({got})"
            raise _undo(link, old, touched, why)
        read_back[name] = confirmed
    link.drain()
    disarmed = link.disarmed_after(link.heartbeats)  # a HEARTBEAT sent after the last write
    if not disarmed:
        why = (
            "armed during the writes"
            if disarmed is False
            else f"silent (no HEARTBEAT within {CONFIRM_HEARTBEAT_S:g} s)"
        )
        raise _undo(link, old, touched, f"vehicle {link.sysid} {why}: not left half-applied")
    changes = tuple(ParamChange(name, old[name], float(value), read_back[name]) for name, value in params.items())
    return ApplyReport(link.sysid, link.compid, changes)
