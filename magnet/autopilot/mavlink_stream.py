"""The samples of MAVLink vehicles as raw batches: one device per vehicle and magnetometer instance, times mapped
to the wire's clock, the vehicle's place, velocity, battery current and throttle attached. Pure: messages (dicts,
with ``sysid``) and the wall clock's ns come in, ``RawBatch`` lists come out (docs/mavlink.md).

Time. A vehicle stamps its messages with the time since it booted. The first message of a vehicle pins its boot time
to the wall clock (offset = now - boot); later messages keep that offset, so their intervals are the vehicle's. The
offset is set again (``resyncs``) when the vehicle's time goes back more than ``BACKWARDS_NS`` (a reboot, or the
32-bit millisecond counter wrapping after 49.7 days) or drifts from the wall clock by more than ``MAX_SKEW_NS``
(a vehicle that was silent, or whose clock runs off). Within a device times never go back: a sample is stamped at
least 1 ns after the one before it.

Attachments. A sample carries the vehicle's last velocity (GLOBAL_POSITION_INT), battery current (SYS_STATUS or
BATTERY_STATUS) and throttle (SERVO_OUTPUT_RAW) when they are at most ``FRESH_NS`` old (wall clock), NaN otherwise;
a batch carries the last place.

A gyroscope that reads zero. ArduPilot fills the gyroscope fields of SCALED_IMU2/3 with zeros when the compass has
no IMU of that number beside it. A reading of exactly zero on all three axes is kept only from a gyroscope that has
read anything else before (a real one at rest rounds to zero now and then); and one that keeps reading exactly zero
while the field turns by ``ZERO_GYRO_TURN_DEG`` is no gyroscope at all: its samples go out without one (the
compass and the calibrator then work from the field and the accelerometer), the device is listed in
``gyro_absent`` until it reads anything else.

Hardware ids (docs/mavlink.md). Instance N is a place in the autopilot's list, not a sensor: a compass missing at boot
moves the ones after it up on some firmware. So the stream asks each vehicle for the id of the sensor behind every
instance (``magnet.autopilot.hwid``: ArduPilot's COMPASS_DEV_ID.., PX4's CAL_MAGn_ID) when it first hears it and again
after every reboot (its boot clock going back), once its autopilot's HEARTBEAT named the component to ask, and each
batch carries the id of its samples' sensor. ``requests``
says what to ask; the PARAM_VALUE answers come in through ``feed``. While a vehicle's ids are being read (at most
``ID_WAIT_NS``) its samples wait, so that none goes out under the id of the sensor that had the instance before;
past that they go out without an id (0) and the ids are asked again every ``ID_RETRY_NS``.
"""

from __future__ import annotations

import collections
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.autopilot import hwid, mavlink
from magnet.autopilot.mavlink_vehicle import Pending, Vehicle
from magnet.wire.raw import RawBatch

SENSOR = "mavlink"
BACKWARDS_NS = 1_000_000_000
MAX_SKEW_NS = 2_000_000_000
FRESH_NS = 1_000_000_000
#: a device's samples wait at most this long (wall clock) before they go out in a short batch
MAX_WAIT_NS = 500_000_000
#: the messages used besides the IMU ones
OTHER_MESSAGES = frozenset(
    {"HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS", "BATTERY_STATUS", "SERVO_OUTPUT_RAW", "PARAM_VALUE"}
)
#: how long a vehicle's samples wait for its compasses' ids (at first contact and after a reboot)
ID_WAIT_NS = 2_000_000_000
#: while the ids are read, the requests go again this often; once given up, the ids are asked again this often
ID_ASK_NS = 500_000_000
ID_RETRY_NS = 30_000_000_000
#: HEARTBEAT types that are not the autopilot (MAV_TYPE: GCS, onboard controller, gimbal, ADS-B, camera, servo,
#: Open Drone ID, battery, log)
NOT_AUTOPILOT_TYPES = frozenset({6, 18, 26, 27, 30, 33, 34, 36, 38})
MAV_AUTOPILOT_INVALID = 8
#: devices one connection may make by default (``--max-port-devices``): a port serves a vehicle or a few dozen, each
#: with up to three compasses; 255 system ids times 256 HIGHRES_IMU ids would be 65,280
MAX_PORT_DEVICES = 64
#: a device whose samples stopped this long (wall clock) gives its place among ``max_devices`` back
#: (``--forget-after``): a flood of ids that fell silent no longer keeps a real vehicle that comes later out
FORGET_NS = 60_000_000_000
FORGET_CHECK_NS = 1_000_000_000


class MavlinkStream:
    """Turns the messages of any number of vehicles into raw batches of ``batch`` samples per device.

    ``feed(message, now_ns)`` takes one message (a dict of its fields with ``mavpackettype`` and ``sysid``);
    ``take(now_ns, flush)`` returns the batches due; ``health(now_ns, timeout_ns)`` says which devices' vehicles
    still send. ``counts`` holds ``messages``, ``samples``, ``ignored`` (types not used), ``resyncs`` and
    ``dropped:<cause>`` per cause; ``last_error`` the last drop's reason.

    At most ``max_devices`` devices: a sample of a new device beyond them is dropped and counted
    (``dropped:device-limit``); the devices already known are unaffected. A device with no sample for ``forget_ns``
    (and none waiting) is forgotten (``forget``, counted ``forgotten``): its place is free for a new one, and it is a
    new device when it sends again; a vehicle silent that long with no device left is forgotten too."""

    def __init__(
        self,
        prefix: str = "mav",
        batch: int = 10,
        motors: int = 4,
        max_devices: int = MAX_PORT_DEVICES,
        forget_ns: int = FORGET_NS,
    ):
        if isinstance(max_devices, bool) or not isinstance(max_devices, int) or max_devices < 1:
            raise ValueError(f"max_devices must be a whole number >= 1, got {max_devices!r}")
        if isinstance(forget_ns, bool) or not isinstance(forget_ns, int) or forget_ns < 1:
            raise ValueError(f"forget_ns must be a whole number of ns >= 1, got {forget_ns!r}")
        self.prefix, self.batch, self.motors, self.max_devices = prefix, batch, motors, max_devices
        self.forget_ns = forget_ns
        self.vehicles: dict[int, Vehicle] = {}
        self.pending: dict[str, Pending] = {}
        self.counts: collections.Counter[str] = collections.Counter()
        self.last_error = ""
        #: devices forgotten since the owner last took them (``take_forgotten``)
        self.forgotten: list[str] = []
        self._forget_checked_ns = 0

    def device(self, sysid: int, instance: int) -> str:
        """The device id of a vehicle's magnetometer: ``<prefix><sysid>-mag<instance>``."""
        return f"{self.prefix}{sysid}-mag{instance}"

    def feed(self, message: Mapping[str, Any], now_ns: int) -> str | None:
        """Take one message; returns the cause when it was dropped (counted), else None."""
        self.counts["messages"] += 1
        kind = message.get("mavpackettype")
        if kind not in mavlink.IMU_MESSAGES and kind not in OTHER_MESSAGES:
            cause = "bad-data" if kind == "BAD_DATA" else None
            self.counts["dropped:bad-data" if cause else "ignored"] += 1
            if cause:
                self.last_error = "bytes that are not a MAVLink message"
            return cause
        sysid = message.get("sysid")
        if isinstance(sysid, bool) or not isinstance(sysid, int) or not 1 <= sysid <= 255:
            return self._drop("bad-field", f"{kind} from system id {sysid!r}, not 1..255")
        vehicle = self.vehicles.setdefault(sysid, Vehicle())
        try:
            self._use(kind, message, sysid, vehicle, now_ns)
        except mavlink.MavlinkError as exc:
            return self._drop(exc.cause, str(exc))
        vehicle.last_seen_ns = now_ns
        return None

    def _drop(self, cause: str, reason: str) -> str:
        self.counts[f"dropped:{cause}"] += 1
        self.last_error = reason
        return cause

    def _use(self, kind: str, message: Mapping[str, Any], sysid: int, vehicle: Vehicle, now_ns: int) -> None:
        if kind in mavlink.IMU_MESSAGES:
            self._sample(mavlink.imu_sample(message), sysid, vehicle, now_ns)
        elif kind == "GLOBAL_POSITION_INT":
            pos = mavlink.position(message)
            vehicle.location = pos.location or vehicle.location
            vehicle.velocity = (pos.vel_ned_ms, now_ns)
        elif kind in ("SYS_STATUS", "BATTERY_STATUS"):
            current = mavlink.battery_current_a(message)
            if current is not None:
                vehicle.current = (current, now_ns)
        elif kind == "SERVO_OUTPUT_RAW":
            value = mavlink.throttle(message, self.motors)
            if value is not None:
                vehicle.throttle = (value, now_ns)
        elif kind == "PARAM_VALUE":
            self._param(message, sysid, vehicle)
        else:
            self._heartbeat(message, vehicle, now_ns)

    def _heartbeat(self, message: Mapping[str, Any], vehicle: Vehicle, now_ns: int) -> None:
        """The autopilot's HEARTBEAT (not a camera's, a gimbal's, a ground station's) says armed and who it is; the
        first one starts the reading of its compasses' ids."""
        if message.get("type") in NOT_AUTOPILOT_TYPES or message.get("autopilot") == MAV_AUTOPILOT_INVALID:
            return
        compid = message.get("compid", 1)
        if vehicle.compid is None:
            vehicle.compid = compid if isinstance(compid, int) else 1
            autopilot = message.get("autopilot")
            vehicle.autopilot = autopilot if isinstance(autopilot, int) else None
            vehicle.asking_ns = now_ns
        if compid == vehicle.compid:
            vehicle.armed = mavlink.armed(message)

    def _param(self, message: Mapping[str, Any], sysid: int, vehicle: Vehicle) -> None:
        """A PARAM_VALUE: an id parameter's answer sets the id of its instance (and of the samples waiting for it)."""
        name = message.get("param_id")
        instance = hwid.instance_of(name) if isinstance(name, str) else None
        if instance is None:
            return
        autopilot = vehicle.autopilot or hwid.MAV_AUTOPILOT_ARDUPILOTMEGA
        if name not in hwid.id_params(autopilot):
            return  # the other autopilot's name
        value, kind = message.get("param_value"), message.get("param_type", 0)
        found = hwid.hardware_id(float(value), int(kind)) if isinstance(value, (int, float)) else None
        if found is None:
            raise mavlink.MavlinkError("bad-field", f"{name} = {value!r} is not a sensor id")
        vehicle.ids[instance] = found
        pending = self.pending.get(self.device(sysid, instance))
        if pending is not None:
            _fill_ids(pending, found)
        if set(vehicle.ids) >= set(hwid.id_params(autopilot).values()):
            self._ids_read(sysid, vehicle)

    def _ids_read(self, sysid: int, vehicle: Vehicle) -> None:
        """Reading ids is over (all answered, or given up): samples still waiting go out with what is known (0
        where nothing is)."""
        vehicle.asking_ns = None
        for pending in self.pending.values():
            if pending.sysid == sysid:
                _fill_ids(pending, 0)

    def requests(self, now_ns: int) -> list[tuple[int, int, str]]:
        """What to ask now, as (system id, component id, parameter name): each vehicle's id parameters not yet
        answered, while its ids are read (every ``ID_ASK_NS``, for at most ``ID_WAIT_NS``) or when a retry is due;
        a vehicle whose ids did not come within ``ID_WAIT_NS`` stops holding its samples."""
        self._expire(now_ns)
        out: list[tuple[int, int, str]] = []
        for sysid, vehicle in self.vehicles.items():
            retry = vehicle.retry_ns is not None and now_ns >= vehicle.retry_ns
            if retry:
                vehicle.retry_ns = now_ns + ID_RETRY_NS
            asking = vehicle.asking_ns is not None and now_ns - vehicle.asked_ns >= ID_ASK_NS
            if not (asking or retry) or vehicle.compid is None:
                continue  # nothing due, or the autopilot not heard yet (its HEARTBEAT names its component)
            vehicle.asked_ns = now_ns
            names = hwid.id_params(vehicle.autopilot or hwid.MAV_AUTOPILOT_ARDUPILOTMEGA)
            out.extend((sysid, vehicle.compid, n) for n, i in names.items() if i not in vehicle.ids)
        return out

    def _expire(self, now_ns: int) -> None:
        """Vehicles whose ids did not all come within ``ID_WAIT_NS``: their samples stop waiting (counted
        ``id-timeouts``); the ids are asked again after ``ID_RETRY_NS``."""
        for sysid, vehicle in self.vehicles.items():
            if vehicle.asking_ns is not None and now_ns - vehicle.asking_ns > ID_WAIT_NS:
                self.counts["id-timeouts"] += 1
                self._ids_read(sysid, vehicle)
                vehicle.retry_ns = now_ns + ID_RETRY_NS

    def hardware_ids(self) -> dict[str, int]:
        """Per device seen: the id of the sensor behind it now (0: none or not known)."""
        return {d: self.vehicles[p.sysid].ids.get(p.instance, 0) for d, p in sorted(self.pending.items())}

    def _time(self, vehicle: Vehicle, boot_ns: int, now_ns: int) -> int:
        """Wall-clock ns of a vehicle's boot time (see the module docstring)."""
        off = vehicle.offset_ns
        rebooted = boot_ns < vehicle.last_boot_ns - BACKWARDS_NS
        if off is None or rebooted or abs(boot_ns + off - now_ns) > MAX_SKEW_NS:
            if off is not None:
                self.counts["resyncs"] += 1
            if rebooted:  # the compasses found at this boot may not be the ones before: their ids are read again
                vehicle.ids.clear()
                vehicle.asked_ns, vehicle.retry_ns = 0, None
                vehicle.asking_ns = now_ns if vehicle.compid is not None else None
            vehicle.offset_ns = off = now_ns - boot_ns
            vehicle.last_boot_ns = boot_ns
        vehicle.last_boot_ns = max(boot_ns, vehicle.last_boot_ns)
        return boot_ns + off

    def _sample(self, sample: mavlink.ImuSample, sysid: int, vehicle: Vehicle, now_ns: int) -> None:
        device = self.device(sysid, sample.instance)
        pending = self.pending.get(device)
        if pending is None:
            if len(self.pending) >= self.max_devices:
                self.forget(now_ns)
            if len(self.pending) >= self.max_devices:
                raise mavlink.MavlinkError(
                    "device-limit",
                    f"{device}: a new device beyond the {self.max_devices} this connection may make",
                )
            pending = self.pending[device] = Pending(sysid, sample.instance)
        t_ns = max(self._time(vehicle, sample.boot_ns, now_ns), pending.last_t_ns + 1)
        known = vehicle.ids.get(sample.instance)
        sensor_id = float(known) if known is not None else (np.nan if vehicle.asking_ns is not None else 0.0)
        pending.last_t_ns, pending.last_ns = t_ns, now_ns
        gyr = sample.gyr_rads if pending.gyro.usable(sample.gyr_rads, sample.mag_ut) else None
        if not pending.rows:
            pending.first_ns = now_ns
        nan3 = np.full(3, np.nan)
        row = np.concatenate(
            [
                sample.mag_ut,
                nan3 if sample.acc_ms2 is None else sample.acc_ms2,
                nan3 if gyr is None else gyr,
                _fresh(vehicle.velocity, now_ns, nan3),
                [_fresh(vehicle.current, now_ns, np.nan), _fresh(vehicle.throttle, now_ns, np.nan), sensor_id],
            ]
        )
        pending.rows.append(row)
        pending.times.append(t_ns)
        self.counts["samples"] += 1

    def take(self, now_ns: int, flush: bool = False) -> list[RawBatch]:
        """The batches due: every device with ``batch`` samples waiting, or whose oldest waited ``MAX_WAIT_NS``
        (all of them when ``flush``); samples whose sensor's id is being read wait (at most ``ID_WAIT_NS``, unless
        ``flush``), and a batch holds the samples of one sensor only. Devices silent ``forget_ns`` are forgotten
        (at most once a second: ``take_forgotten`` says which)."""
        self._expire(now_ns)
        if now_ns - self._forget_checked_ns >= FORGET_CHECK_NS:
            self._forget_checked_ns = now_ns
            self.forget(now_ns)
            self._forget_vehicles(now_ns)
        out = []
        for device, pending in self.pending.items():
            due = len(pending.rows) >= self.batch or now_ns - pending.first_ns >= MAX_WAIT_NS or flush
            while pending.rows and due and (flush or not np.isnan(pending.rows[0][14])):
                out.append(self._batch(device, pending))
                due = len(pending.rows) >= self.batch or flush
        return out

    def _batch(self, device: str, pending: Pending) -> RawBatch:
        first = pending.rows[0][14]
        count = 1
        while count < min(self.batch, len(pending.rows)) and _same(pending.rows[count][14], first):
            count += 1
        rows, pending.rows = pending.rows[:count], pending.rows[count:]
        times, pending.times = pending.times[:count], pending.times[count:]
        table = np.array(rows)
        pending.seq += 1
        return RawBatch(
            device,
            pending.seq - 1,
            SENSOR,
            np.array(times, dtype=np.int64),
            table[:, 0:3],
            _columns(table[:, 3:6]),
            None,
            _columns(table[:, 6:9]),
            self.vehicles[pending.sysid].location,
            _columns(table[:, 9:12]),
            _values(table[:, 12]),
            _values(table[:, 13]),
            hardware_id=0 if np.isnan(first) else int(first),
        )

    def take_forgotten(self) -> list[str]:
        """The devices forgotten since the last call (the edge frees their tokens and places)."""
        out, self.forgotten = self.forgotten, []
        return out

    def forget(self, now_ns: int) -> list[str]:
        """Forget the devices with no sample for ``forget_ns`` and none waiting to go out; their ids (each counted
        ``forgotten``). Called by ``take`` (so the edge hears of them), and when a new device finds no place."""
        gone = [d for d, p in self.pending.items() if not p.rows and now_ns - p.last_ns >= self.forget_ns]
        for device in gone:
            del self.pending[device]
        self.counts["forgotten"] += len(gone)
        self.forgotten.extend(gone)
        return gone

    def _forget_vehicles(self, now_ns: int) -> None:
        """Forget the vehicles silent for ``forget_ns`` with no device left (a flood's system ids, and those whose
        every sample was refused): what was known of them (clock, ids, place) is learnt again if they come back, as
        after a reboot. Only from ``take``: a sample being fed holds its vehicle."""
        devices = {p.sysid for p in self.pending.values()}
        silent = [s for s, v in self.vehicles.items() if now_ns - v.last_seen_ns >= self.forget_ns]
        for sysid in silent:
            if sysid not in devices:
                del self.vehicles[sysid]

    @property
    def gyro_absent(self) -> list[str]:
        """The devices whose gyroscope reads exactly zero while their field turns (module docstring), sorted."""
        return sorted(d for d, p in self.pending.items() if p.gyro.absent)

    def health(self, now_ns: int, timeout_ns: int) -> dict[str, bool]:
        """Per device seen: whether its vehicle sent anything in the last ``timeout_ns``."""
        return {d: now_ns - self.vehicles[p.sysid].last_seen_ns <= timeout_ns for d, p in self.pending.items()}


def _same(a: float, b: float) -> bool:
    """Two rows' hardware ids are one (NaN, being read, equal to NaN)."""
    return a == b or (np.isnan(a) and np.isnan(b))


def _fill_ids(pending: Pending, sensor_id: int) -> None:
    """Rows waiting for their sensor's id (NaN) get ``sensor_id``."""
    for row in pending.rows:
        if np.isnan(row[14]):
            row[14] = sensor_id


def _fresh(value: tuple[Any, int] | None, now_ns: int, default: Any) -> Any:
    return default if value is None or now_ns - value[1] > FRESH_NS else value[0]


def _columns(block: np.ndarray) -> np.ndarray | None:
    """(N, 3) when every row is known, None when none is, rows of NaN left where some are (velocity)."""
    known = np.isfinite(block).all(axis=1)
    return None if not known.any() else block


def _values(column: np.ndarray) -> np.ndarray | None:
    return None if np.isnan(column).all() else column


def compass_instance(device: str | None) -> int | None:
    """The compass instance (0-based) a device id of ``MavlinkStream.device`` names (``mav1-mag2``: 2); None for an
    id of another form."""
    found = re.fullmatch(r"[A-Za-z0-9_]*\d+-mag(\d)", device or "")
    return int(found.group(1)) if found else None
