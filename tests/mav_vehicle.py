"""A MAVLink vehicle stand-in for tests, run as its own process: ``python tests/mav_vehicle.py --url udpout:HOST:PORT``.

It sends, with pymavlink, what an ArduPilot vehicle sends about its compasses, from the simulator's truth
(``magnet.simulator``; a tumble, each compass with its own hard and soft iron): HEARTBEAT (1 Hz, the armed flag from
``--armed``), RAW_IMU (compass 0) and SCALED_IMU2 (compass 1) at ``--rate``, ATTITUDE (10 Hz), GLOBAL_POSITION_INT
(5 Hz, the simulator's place), SYS_STATUS (2 Hz). It answers PARAM_SET, PARAM_REQUEST_READ and PARAM_REQUEST_LIST
with PARAM_VALUE from its parameter table (a few ArduPilot compass parameters). At the end (``--duration`` or
SIGTERM) it writes ``--truth FILE.npz``: per IMU message sent, the compass instance, the field sent (milligauss) and
the true heading and pitch, so a test can join what the compass published to the truth by the field.

Faults and poses a vehicle shows (issue 27): ``--zero-gyro N`` sends compass N's gyroscope fields as zero during
the tumble (ArduPilot's SCALED_IMU2 when a second compass has no second IMU beside it); ``--hold-after S
--hold-yaw D`` ends the tumble after S seconds: the vehicle settles over ``SETTLE_S`` to level at true heading D
(its gyroscope reading the rates that carry it there) and stays, GLOBAL_POSITION_INT's velocity zero throughout.
``--quad``: instead of the tumble, a quadcopter's flight (the simulator's multirotor, its motors' throttle and current)
with three compasses (``QUAD``): the first as it should be, the second mounted turned 90 deg in yaw, the third beside
the power wires (SCALED_IMU3); SYS_STATUS (current), SERVO_OUTPUT_RAW (throttle) and GLOBAL_POSITION_INT (velocity)
at 10 Hz. ``--clean``: compasses without errors (as ArduPilot sends a field it has corrected). ``--pause-at S
--pause-s D``: no IMU message for D seconds from S (a radio dropout; the boot clock goes on).

Hardware ids (issue 27, item 5): the compasses' ids (``SENSOR_IDS``) are parameters as ArduPilot names them
(``COMPASS_DEV_ID``, ``COMPASS_DEV_ID2``, ``COMPASS_DEV_ID3``), answered as MAV_PARAM_TYPE_INT32 with the integer in
the float as ArduPilot sends it. ``--reboot-at S --missing N``: after S seconds the vehicle reboots (its boot clock
starts again from 0) without compass N: the compasses after it move up one instance (as firmware that numbers them as
found does), each with its own errors and id, and the id parameters say so.

The compass parameters act as ArduPilot's do (issue 27, item 7): each compass's field is sent corrected by its
``COMPASS_OFS*``, ``COMPASS_DIA*``, ``COMPASS_ODI*``, ``COMPASS_SCALE*`` (all at their defaults: as measured), so a
test sees what an apply changed; a COMMAND_LONG MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN (1: reboot) is acknowledged and the
vehicle falls silent for ``REBOOT_SILENT_S`` and boots again (refused, MAV_RESULT_DENIED, while armed).
``--param NAME=VALUE`` sets a parameter at start (a vehicle that holds an older calibration).

Parameter faults (issue 32, ``export --apply``): ``--no-confirm NAME`` takes a PARAM_SET of NAME without answering
it (a read is answered); ``--clamp NAME=MAX`` holds at most MAX in NAME and answers with what it holds;
``--arm-after-sets N`` arms after its Nth PARAM_SET and says so in a HEARTBEAT at once; ``--camera``: a camera
(component 100, MAV_TYPE_CAMERA, MAV_AUTOPILOT_INVALID) on the same system sends "disarmed" heartbeats at 10 Hz.
"""

from __future__ import annotations

import argparse
import math
import signal
import time
from typing import Any

import numpy as np
from pymavlink import mavutil

from magnet.autopilot.verify import ardupilot_correction
from magnet.frames import (
    euler_to_quaternion,
    quaternion_conjugate,
    quaternion_multiply,
    quaternion_to_euler,
    quaternion_to_matrix,
    quaternion_to_rotation_vector,
)
from magnet.simulator import SensorErrors, SensorStream, SimulatorConfig
from magnet.simulator.motion import G_NED
from magnet.simulator.motors import Motors

SOFT_0 = ((1.08, 0.03, 0.0), (0.03, 0.95, 0.02), (0.0, 0.02, 1.0))
SOFT_1 = ((0.96, -0.02, 0.01), (-0.02, 1.05, 0.0), (0.01, 0.0, 1.1))
COMPASSES = {  # instance -> its errors (hard iron uT, soft iron)
    0: SensorErrors(hard_iron_ut=(25.0, -12.0, 9.0), soft_iron=SOFT_0),
    1: SensorErrors(hard_iron_ut=(-8.0, 30.0, -14.0), soft_iron=SOFT_1),
}
#: each compass's hardware id (ArduPilot's packing: bus type | bus << 3 | address << 8 | devtype << 16)
SENSOR_IDS = {0: 466441, 1: 131874, 2: 97539}
PARAMETERS = {
    "COMPASS_DEV_ID": float(SENSOR_IDS[0]),
    "COMPASS_DEV_ID2": float(SENSOR_IDS[1]),
    "COMPASS_DEV_ID3": 0.0,
    "COMPASS_OFS_X": 0.0,
    "COMPASS_OFS_Y": 0.0,
    "COMPASS_OFS_Z": 0.0,
    "COMPASS_DIA_X": 1.0,
    "COMPASS_DIA_Y": 1.0,
    "COMPASS_DIA_Z": 1.0,
    "COMPASS_ODI_X": 0.0,
    "COMPASS_ODI_Y": 0.0,
    "COMPASS_ODI_Z": 0.0,
    "COMPASS_SCALE": 0.0,
    "COMPASS_MOTCT": 0.0,
    "COMPASS_MOT_X": 0.0,
    "COMPASS_MOT_Y": 0.0,
    "COMPASS_MOT_Z": 0.0,
}
#: the quadcopter's compasses (``--quad``): instance -> (errors, the motors' field at it, uT per A)
QUAD = {
    0: (SensorErrors(), (0.0, 0.0, 0.0)),
    1: (SensorErrors(misalignment_deg=(0.0, 0.0, 90.0)), (0.0, 0.0, 0.0)),  # mounted turned: COMPASS_ORIENT2 = 2
    2: (SensorErrors(), (0.3, -0.2, 0.25)),  # beside the power wires: 18 uT at the 40 A of full throttle
}
REAL32 = mavutil.mavlink.MAV_PARAM_TYPE_REAL32
INT32 = mavutil.mavlink.MAV_PARAM_TYPE_INT32
REBOOT = mavutil.mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN
SETTLE_S = 2.0  # from the tumble's last attitude to level at --hold-yaw
REBOOT_SILENT_S = 1.0  # a commanded reboot: nothing sent for this long


def _slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    angle = math.acos(min(dot, 1.0))
    if angle < 1e-9:
        return q0
    q = (math.sin((1 - s) * angle) * q0 + math.sin(s * angle) * q1) / math.sin(angle)
    return q / np.linalg.norm(q)


class Held:
    """A compass's stream after the tumble: settles from its last attitude to level at ``yaw_deg`` (true) over
    ``SETTLE_S`` (smoothstep), then holds; the field, specific force and rates from its errors, with noise."""

    def __init__(self, stream: SensorStream, yaw_deg: float, rate_hz: float, seed: int) -> None:
        self.stream, self.rate_hz = stream, rate_hz
        self.errors = _noise(stream.config.errors)
        self.start = np.array(stream.last_truth["quat_wxyz"], dtype=float)
        self.end = euler_to_quaternion(yaw_deg, 0.0, 0.0).reshape(4)
        self.previous, self.k = self.start, 0
        self.rng = np.random.default_rng(seed + 100)
        self.b_ned = np.array(stream.earth.ned_ut)
        self.last_truth: dict[str, Any] = dict(stream.last_truth)

    def measure_imu(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        self.k += 1
        s = min(1.0, self.k / (SETTLE_S * self.rate_hz))
        q = _slerp(self.start, self.end, s * s * (3 - 2 * s))
        turn = quaternion_multiply(quaternion_conjugate(self.previous[None]), q[None])
        rate = quaternion_to_rotation_vector(turn)[0] * self.rate_hz
        self.previous = q
        rotation = quaternion_to_matrix(q[None])[0]
        e = self.errors
        mag = e.distortion @ (rotation.T @ self.b_ned) + e.hard_iron_ut + e.noise_ut * self.rng.standard_normal(3)
        acc = rotation.T @ (-G_NED) + e.acc_noise_ms2 * self.rng.standard_normal(3)
        gyr = rate + e.gyro_noise_rads * self.rng.standard_normal(3)
        heading, pitch, roll = (float(v[0]) for v in quaternion_to_euler(q[None]))
        self.last_truth = {"heading_deg": heading, "pitch_deg": pitch, "roll_deg": roll, "quat_wxyz": tuple(q)}
        return mag, acc, gyr


def _noise(errors: SensorErrors) -> SensorErrors:
    import dataclasses

    return dataclasses.replace(errors, noise_ut=0.3, acc_noise_ms2=0.02, gyro_noise_rads=0.002)


class Vehicle:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.conn = mavutil.mavlink_connection(args.url, source_system=args.sysid, source_component=1)
        rate, count = max(args.rate, 1.0), args.samples
        self.streams: dict[int, Any] = {
            i: SensorStream(SimulatorConfig(trajectory="tumble", rate_hz=rate, count=count, errors=_noise(e), seed=i))
            for i, e in COMPASSES.items()
        }
        if args.clean:
            self.streams = {
                i: SensorStream(
                    SimulatorConfig("tumble", rate_hz=rate, count=count, errors=_noise(SensorErrors()), seed=i)
                )
                for i in COMPASSES
            }
        if args.quad:  # one flight (one seed) seen by three compasses
            self.streams = {
                i: SensorStream(
                    SimulatorConfig("multirotor", rate_hz=rate, errors=_noise(e), seed=7, motors=Motors(ut_per_a=m))
                )
                for i, (e, m) in QUAD.items()
            }
        self.params = dict(PARAMETERS)
        self.params.update({n: float(v) for n, v in (p.split("=") for p in args.param)})
        self.silent_until = 0.0
        self.sensors = {i: SENSOR_IDS[i] for i in self.streams}  # instance -> the id of the compass behind it
        self._say_ids()
        self.boot_k = 0  # the IMU message count at the last boot
        self.k = 0  # IMU messages so far
        self.reboots = 0  # commanded reboots
        self.sets = 0
        self.clamp = {n: float(v) for n, v in (c.split("=") for c in args.clamp)}
        self.truth: list[tuple[int, int, int, int, float, float]] = []
        self.sent_by: list[int] = []  # per truth row: the id of the compass that sent it
        self.boot = time.monotonic()

    def boot_ms(self) -> int:
        return int((time.monotonic() - self.boot) * 1000)

    def _say_ids(self) -> None:
        for instance, name in enumerate(("COMPASS_DEV_ID", "COMPASS_DEV_ID2", "COMPASS_DEV_ID3")):
            self.params[name] = float(self.sensors.get(instance, 0))

    def reboot(self, k: int, missing: int | None) -> None:
        """Boot again without compass ``missing`` (None: all there): the ones after it move up an instance (module
        docstring)."""
        kept = [(self.streams[i], self.sensors[i]) for i in sorted(self.streams) if i != missing]
        self.streams = {i: stream for i, (stream, _) in enumerate(kept)}
        self.sensors = {i: sensor for i, (_, sensor) in enumerate(kept)}
        self._say_ids()
        self.boot_k = k
        self.boot = time.monotonic()

    def send_imu(self, k: int) -> None:
        mav = self.conn.mav
        if self.args.reboot_at is not None and self.boot_k == 0 and k == int(self.args.reboot_at * self.args.rate):
            self.reboot(k, self.args.missing)
        if time.monotonic() < self.silent_until:
            return
        boot_ms = int((k - self.boot_k) * 1000 / self.args.rate)
        if self.args.hold_after is not None and k == int(self.args.hold_after * self.args.rate):
            self.streams = {i: Held(s, self.args.hold_yaw, self.args.rate, i) for i, s in self.streams.items()}
        for instance, stream in self.streams.items():
            mag, acc, gyr = stream.measure_imu()
            m = np.round(self.corrected(instance, mag[None] * 10.0)[0]).astype(int)  # uT -> milligauss, corrected
            a = np.round(acc / 9.80665 * 1000).astype(int)  # m/s^2 -> milli-g
            g = np.round(gyr * 1000).astype(int)  # rad/s -> mrad/s
            if instance == self.args.zero_gyro and not isinstance(stream, Held):
                g = np.zeros(3, dtype=int)
            if instance == 0:
                mav.raw_imu_send(boot_ms * 1000, *a, *g, *m)
            elif instance == 1:
                mav.scaled_imu2_send(boot_ms, *a, *g, *m)
            else:
                mav.scaled_imu3_send(boot_ms, *a, *g, *m)
            truth = stream.last_truth
            self.truth.append((instance, *m.tolist(), truth["heading_deg"], truth["pitch_deg"]))
            self.sent_by.append(self.sensors.get(instance, 0))
        if k % max(1, int(self.args.rate / 10)) == 0:
            t = self.streams[0].last_truth
            roll, pitch, yaw = (math.radians(t[name]) for name in ("roll_deg", "pitch_deg", "heading_deg"))
            mav.attitude_send(boot_ms, roll, pitch, yaw, 0, 0, 0)

    def corrected(self, instance: int, reading_mg: np.ndarray) -> np.ndarray:
        """What ArduPilot sends for compass ``instance``'s readings (N, 3) mGauss: its parameters applied."""
        return ardupilot_correction(self.params, instance, 0).field(reading_mg)

    def send_slow(self, tick: int) -> None:
        """Every 100 ms: position at 5 Hz, status at 2 Hz, heartbeat at 1 Hz (a quadcopter's flight: position,
        current and throttle at 10 Hz)."""
        mav = self.conn.mav
        if time.monotonic() < self.silent_until:
            return
        if self.args.quad:
            self.send_flight()
        if tick % 2 == 0 and not self.args.quad:
            mav.global_position_int_send(self.boot_ms(), 504500000, 305200000, 180000, 0, 0, 0, 0, 0)
        if tick % 5 == 0 and not self.args.quad:
            mav.sys_status_send(0, 0, 0, 500, 16000, 1200, 80, 0, 0, 0, 0, 0, 0)
        if self.args.camera:  # the first heartbeat heard
            self.send_camera_heartbeat()
        if tick % 10 == 0:
            self.send_heartbeat()
            if self.args.camera:  # and the last of each second
                self.send_camera_heartbeat()

    def send_camera_heartbeat(self) -> None:
        mav = self.conn.mav
        mav.srcComponent = mavutil.mavlink.MAV_COMP_ID_CAMERA
        camera, invalid = mavutil.mavlink.MAV_TYPE_CAMERA, mavutil.mavlink.MAV_AUTOPILOT_INVALID
        mav.heartbeat_send(camera, invalid, 0, 0, mavutil.mavlink.MAV_STATE_ACTIVE)
        mav.srcComponent = 1

    def send_heartbeat(self) -> None:
        armed = mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.args.armed else 0
        self.conn.mav.heartbeat_send(
            mavutil.mavlink.MAV_TYPE_QUADROTOR,
            mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
            armed | mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
            0,
            mavutil.mavlink.MAV_STATE_ACTIVE if self.args.armed else mavutil.mavlink.MAV_STATE_STANDBY,
        )

    def send_flight(self) -> None:
        truth, mav = self.streams[0].last_truth, self.conn.mav
        if "current_a" not in truth:
            return
        vel = [0 if v is None or not math.isfinite(v) else round(v * 100) for v in truth["vel_ned_ms"] or ()]
        mav.global_position_int_send(self.boot_ms(), 504500000, 305200000, 180000, 0, *(vel or [0, 0, 0]), 0)
        mav.sys_status_send(0, 0, 0, 500, 16000, round(truth["current_a"] * 100), 80, 0, 0, 0, 0, 0, 0)
        pwm = round(1000 + 1000 * truth["throttle"])
        mav.servo_output_raw_send(self.boot_ms() * 1000, 0, pwm, pwm, pwm, pwm, 0, 0, 0, 0)

    def send_param(self, name: str) -> None:
        names = list(self.params)
        kind = INT32 if name.startswith("COMPASS_DEV_ID") else REAL32
        self.conn.mav.param_value_send(name.encode(), self.params[name], kind, len(names), names.index(name))

    def set_param(self, name: str, value: float) -> None:
        self.params[name] = min(value, self.clamp.get(name, math.inf))
        self.sets += 1
        if name != self.args.no_confirm:
            self.send_param(name)
        if self.sets == self.args.arm_after_sets:
            self.args.armed = True
            self.send_heartbeat()

    def command_reboot(self) -> None:
        """MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: refused while armed; else acknowledged, then silent, then booted."""
        mav = mavutil.mavlink
        if self.args.armed:
            self.conn.mav.command_ack_send(REBOOT, mav.MAV_RESULT_DENIED)
            return
        self.conn.mav.command_ack_send(REBOOT, mav.MAV_RESULT_ACCEPTED)
        self.reboots += 1
        self.silent_until = time.monotonic() + REBOOT_SILENT_S
        self.reboot(self.k, None)

    def answer(self) -> None:
        while (message := self.conn.recv_match(blocking=False)) is not None:
            kind = message.get_type()
            if kind == "PARAM_SET" and message.param_id in self.params:
                self.set_param(message.param_id, float(message.param_value))
            elif kind == "PARAM_REQUEST_READ":
                names = list(self.params)
                name = message.param_id if message.param_index < 0 else names[message.param_index]
                if name in self.params:
                    self.send_param(name)
            elif kind == "COMMAND_LONG" and message.command == REBOOT and round(message.param1) == 1:
                self.command_reboot()
            elif kind == "PARAM_REQUEST_LIST":
                for name in self.params:
                    self.send_param(name)

    def run(self) -> None:
        stop: list[bool] = []
        signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
        start, k, tick = time.monotonic(), 0, 0
        while not stop and time.monotonic() - start < self.args.duration:
            now = time.monotonic() - start
            # what is due, in the order of its time: a stand-in that was not scheduled for a while sends the IMU
            # messages and the slow ones (current, throttle) interleaved as a vehicle would have, not all of one first
            while (imu_due := self.args.rate > 0 and k < now * self.args.rate) or tick < now * 10:
                if imu_due and (tick >= now * 10 or k / self.args.rate <= tick / 10):
                    paused = (
                        self.args.pause_at is not None
                        and 0 <= k / self.args.rate - self.args.pause_at < self.args.pause_s
                    )
                    if not paused:
                        self.send_imu(k)
                    k += 1
                    self.k = k
                else:
                    self.send_slow(tick)
                    tick += 1
            self.answer()
            time.sleep(0.002)
        if self.args.truth:
            table: Any = np.array(self.truth) if self.truth else np.empty((0, 6))
            np.savez(
                self.args.truth,
                table=table,
                params=np.array([self.params[n] for n in PARAMETERS]),
                sensors=np.array(self.sent_by, dtype=np.int64),
                reboots=np.array(self.reboots),
            )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--url", required=True)
    parser.add_argument("--sysid", type=int, default=1)
    parser.add_argument("--rate", type=float, default=50.0, help="IMU messages per second per compass (0: none)")
    parser.add_argument("--samples", type=int, default=3000, help="samples per run of the simulated tumble")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--armed", action="store_true")
    parser.add_argument("--truth")
    parser.add_argument("--zero-gyro", type=int, help="this compass's gyroscope fields sent as zero in the tumble")
    parser.add_argument("--hold-after", type=float, help="seconds of tumble before settling and holding still")
    parser.add_argument("--hold-yaw", type=float, default=70.0, help="the true heading held (deg)")
    parser.add_argument("--quad", action="store_true", help="a quadcopter's flight with three compasses (QUAD)")
    parser.add_argument("--clean", action="store_true", help="compasses without errors (a corrected field)")
    parser.add_argument("--pause-at", type=float, help="seconds into the run: no IMU message for --pause-s")
    parser.add_argument("--pause-s", type=float, default=1.0)
    parser.add_argument("--reboot-at", type=float, help="seconds into the run: reboot without compass --missing")
    parser.add_argument("--missing", type=int, default=0, help="the compass not found at the reboot")
    parser.add_argument("--param", action="append", default=[], help="NAME=VALUE: a parameter's value at start")
    parser.add_argument("--no-confirm", help="a PARAM_SET of this parameter is taken but never answered")
    parser.add_argument("--clamp", action="append", default=[], help="NAME=MAX: the most this parameter holds")
    parser.add_argument("--arm-after-sets", type=int, help="arms after this many PARAM_SETs (a HEARTBEAT at once)")
    parser.add_argument("--camera", action="store_true", help="a camera on this system sends disarmed heartbeats")
    Vehicle(parser.parse_args()).run()


if __name__ == "__main__":
    main()
