"""After ``magnet export --apply`` (issue 27, item 7; docs/mavlink.md): the autopilot is rebooted (``--reboot``,
MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, refused while armed) or told to be, then the vehicle's own corrected field is
watched for ``--check-s`` seconds and checked against what the record predicts (``magnet.autopilot.verify``); when it
sends more than one compass, they are also compared with each other (``magnet.vehicle.judge``, docs/vehicles.md)."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping
from typing import Any

import numpy as np
from pymavlink import mavutil

from magnet.autopilot import mavlink
from magnet.autopilot.verify import AfterApply, check_after_apply
from magnet.model import Calibration
from magnet.vehicle import Series, VehicleReport, judge
from services.commands.export_apply import HEARTBEAT_TIMEOUT_S, ApplyError, _Link

#: how long the autopilot has to acknowledge the reboot, and to send IMU messages again after it
ACK_TIMEOUT_S = 3.0
BACK_TIMEOUT_S = 30.0
REBOOT_NOTE = (
    "reboot the autopilot before flying, so that every compass parameter is in force and its estimator starts from "
    "the corrected field (--reboot does it)"
)


@dataclasses.dataclass(frozen=True)
class AfterReport:
    """What followed the apply: whether the autopilot was rebooted, the check of the applied compass (None when not
    checked), and the vehicle's compasses compared (None with fewer than two)."""

    rebooted: bool
    check: AfterApply | None
    vehicle: VehicleReport | None

    def lines(self) -> list[str]:
        out = ["autopilot rebooted" if self.rebooted else REBOOT_NOTE]
        if self.check is not None:
            out.append(f"check: {self.check.summary}")
        if self.vehicle is not None:
            out.append(f"compasses: {self.vehicle.summary}")
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "rebooted": self.rebooted,
            "check": None if self.check is None else self.check.to_dict(),
            "vehicle": None if self.vehicle is None else self.vehicle.to_dict(),
        }


def reboot(link: _Link) -> None:
    """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (param1 1: the autopilot) to the linked autopilot; ApplyError while it is
    armed (nothing sent) or when it does not accept."""
    link.drain()
    if link.armed:
        raise ApplyError(f"vehicle {link.sysid} is armed: not rebooted (disarm it, then reboot it)")
    command = mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN
    link.conn.mav.command_long_send(link.sysid, link.compid, command, 0, 1, 0, 0, 0, 0, 0, 0)
    deadline = time.monotonic() + ACK_TIMEOUT_S
    while (left := deadline - time.monotonic()) > 0:
        ack = link.wait("COMMAND_ACK", left)
        if ack is not None and ack.command == command:
            if ack.result != mavutil.mavlink.MAV_RESULT_ACCEPTED:
                raise ApplyError(f"vehicle {link.sysid} refused the reboot (MAV_RESULT {ack.result})")
            return
    raise ApplyError(f"vehicle {link.sysid} did not acknowledge the reboot within {ACK_TIMEOUT_S:g} s")


def watch(link: _Link, seconds: float, start_timeout_s: float) -> dict[int, list[tuple[float, np.ndarray]]]:
    """The autopilot's compasses for ``seconds`` from its first IMU message (waited for at most
    ``start_timeout_s``): per instance, (boot time s, field mGauss (3,)) as it sent them."""
    out: dict[int, list[tuple[float, np.ndarray]]] = {}
    kinds = sorted(mavlink.IMU_MESSAGES)
    end = time.monotonic() + start_timeout_s
    started = False
    while (left := end - time.monotonic()) > 0:
        message = link.conn.recv_match(type=kinds, blocking=True, timeout=min(left, 0.5))
        if message is None or message.get_srcSystem() != link.sysid:
            continue
        try:
            sample = mavlink.imu_sample(mavlink.message_dict(message))
        except mavlink.MavlinkError:
            continue  # a compass with no field (zeros): none there
        if not started:
            started, end = True, time.monotonic() + seconds
        field_mg = np.asarray(sample.mag_ut, dtype=float) * 10.0
        out.setdefault(sample.instance, []).append((sample.boot_ns * 1e-9, field_mg))
    return out


def after_apply(
    url: str,
    baud: int,
    sysid: int,
    calibration: Calibration,
    instance: int,
    before: Mapping[str, float],
    after: Mapping[str, float],
    *,
    rotation_in_force: int = 0,
    do_reboot: bool = False,
    check_s: float = 60.0,
) -> AfterReport:
    """Reboot (``do_reboot``) and check (``check_s`` > 0) the vehicle ``sysid`` at ``url`` after its parameters
    ``before`` -> ``after`` were applied for ``calibration`` on compass ``instance`` (module docstring)."""
    link = _Link(url, baud, sysid)
    try:
        if link.wait("HEARTBEAT", HEARTBEAT_TIMEOUT_S) is None:
            raise ApplyError(
                f"{url}: vehicle {sysid} sent no HEARTBEAT within {HEARTBEAT_TIMEOUT_S:g} s after the apply"
            )
        if do_reboot:
            reboot(link)
        if check_s <= 0:
            return AfterReport(do_reboot, None, None)
        seen = watch(link, check_s, BACK_TIMEOUT_S if do_reboot else HEARTBEAT_TIMEOUT_S)
    finally:
        link.close()
    sent = np.array([f for _, f in seen.get(instance, [])]).reshape(-1, 3)
    check = check_after_apply(calibration, before, after, instance, sent, rotation_in_force)
    return AfterReport(do_reboot, check, _compared(sysid, seen))


def _compared(sysid: int, seen: Mapping[int, list[tuple[float, np.ndarray]]]) -> VehicleReport | None:
    """The vehicle's compasses compared with each other over the check (two or more needed)."""
    if len(seen) < 2:
        return None
    series = {}
    for instance, rows in seen.items():
        t_s = np.array([t for t, _ in rows])
        field_ut = np.array([f for _, f in rows]) * 0.1
        nan = np.full(len(rows), np.nan)
        series[f"mav{sysid}-mag{instance}"] = Series(t_s, field_ut, nan, nan)
    return judge(f"mav{sysid}", series)
