"""Parameters onto a vehicle over MAVLink: ``apply_params(url, params)`` for ``magnet export --apply URL``.

The exchange (MAVLink's parameter protocol, docs/mavlink.md): wait for the vehicle's HEARTBEAT (its system and
component id, and ``base_mode``); refuse while it is armed (MAV_MODE_FLAG_SAFETY_ARMED), since a compass changing
under a flying vehicle's estimator is a hazard; read each parameter's value now (PARAM_REQUEST_READ -> PARAM_VALUE);
set it (PARAM_SET, as a 32-bit float) and read the vehicle's answer (PARAM_VALUE of that name), retrying a few times;
a value read back that is not the one sent (as a 32-bit float) is an error. The report lists every parameter with
its old and new value.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from pymavlink import mavutil

HEARTBEAT_TIMEOUT_S = 5.0
ANSWER_TIMEOUT_S = 1.0
ATTEMPTS = 3
MAX_NAME_CHARS = 16  # PARAM_SET.param_id is 16 characters
GCS_TYPES = {mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_TYPE_ONBOARD_CONTROLLER}


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
    """One MAVLink connection to one vehicle (the first that sends a HEARTBEAT), watching its armed flag."""

    def __init__(self, url: str, baud: int, sysid: int | None) -> None:
        try:
            self.conn = mavutil.mavlink_connection(url, baud=baud, source_system=255, source_component=190)
        except Exception as exc:  # pymavlink raises what its transport raises (OSError, OverflowError, ...)
            raise ApplyError(f"{url}: cannot open it: {exc}") from None
        self.want = sysid
        self.sysid = self.compid = 0
        self.armed = False

    def close(self) -> None:
        self.conn.close()

    def _heartbeat(self, message: Any) -> None:
        if message.type in GCS_TYPES or (self.want is not None and message.get_srcSystem() != self.want):
            return
        if not self.sysid:
            self.sysid, self.compid = message.get_srcSystem(), message.get_srcComponent()
        if message.get_srcSystem() == self.sysid:
            self.armed = bool(message.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def wait(self, kind: str, timeout_s: float, name: str | None = None) -> Any:
        """The next message of ``kind`` from the vehicle (PARAM_VALUE: of ``name``), or None after ``timeout_s``;
        heartbeats seen meanwhile update the armed flag."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            message = self.conn.recv_match(type=["HEARTBEAT", kind], blocking=True, timeout=left)
            if message is None:
                return None
            if message.get_type() == "HEARTBEAT":
                self._heartbeat(message)
                if kind == "HEARTBEAT" and self.sysid:
                    return message
                continue
            if message.get_srcSystem() != self.sysid:
                continue
            if name is None or message.param_id == name:
                return message
        return None

    def refuse_if_armed(self) -> None:
        if self.armed:
            raise ApplyError(
                f"vehicle {self.sysid} is armed: its compass parameters are not changed in flight; disarm it and "
                "apply again"
            )

    def read(self, name: str) -> float | None:
        for _ in range(ATTEMPTS):
            self.conn.mav.param_request_read_send(self.sysid, self.compid, name.encode(), -1)
            answer = self.wait("PARAM_VALUE", ANSWER_TIMEOUT_S, name)
            if answer is not None:
                return float(answer.param_value)
        return None

    def set(self, name: str, value: float) -> float:
        sent = np.float32(value)
        for _ in range(ATTEMPTS):
            self.refuse_if_armed()
            self.conn.mav.param_set_send(
                self.sysid, self.compid, name.encode(), float(sent), mavutil.mavlink.MAV_PARAM_TYPE_REAL32
            )
            answer = self.wait("PARAM_VALUE", ANSWER_TIMEOUT_S, name)
            if answer is not None and np.float32(answer.param_value) == sent:
                return float(answer.param_value)
        raise ApplyError(
            f"vehicle {self.sysid} did not take {name} = {float(sent):g} after {ATTEMPTS} tries "
            "(no PARAM_VALUE, or another value read back)"
        )


def apply_params(url: str, params: Mapping[str, float], *, baud: int = 57600, sysid: int | None = None) -> ApplyReport:
    """Set ``params`` (name -> value) on the vehicle at ``url`` (a pymavlink URL: udpin:HOST:PORT, udpout:..., tcp:...,
    or a serial device at ``baud``), reading each back; ``sysid`` picks a vehicle (default: the first heard).
    ApplyError (a ValueError) when no vehicle answers, it is armed, it has no such parameter, or a value does not
    stick; parameters set before such an error stay set (the report of a later run shows them unchanged)."""
    _check(params)
    link = _Link(url, baud, sysid)
    try:
        if link.wait("HEARTBEAT", HEARTBEAT_TIMEOUT_S) is None:
            raise ApplyError(f"{url}: no vehicle's HEARTBEAT within {HEARTBEAT_TIMEOUT_S:g} s")
        link.refuse_if_armed()
        old = {}
        for name in params:
            old[name] = link.read(name)
            if old[name] is None:
                raise ApplyError(f"vehicle {link.sysid} does not answer for parameter {name}: is it its name?")
        changes = tuple(
            ParamChange(name, old[name], float(value), link.set(name, value)) for name, value in params.items()
        )
        return ApplyReport(link.sysid, link.compid, changes)
    finally:
        link.close()
