"""Where ``magnet edge``'s samples come from: each source has the one shape of ``services.edge.source.Source``, and
``make_source`` opens the one the settings name through one table, ``SOURCES`` (the settings' ``SourceKind`` ->
constructor). To add a source: write its class (the ``Source`` methods) and add its row here (and, for a new
option, its kind to ``services.edge.settings``).

- ``FleetSource``: N simulated devices, one vectorized step per batch.
- ``StreamSource``: one simulated device read sample by sample (no register emulation).
- ``ChipSource``: one chip through its driver (a real bus, or the chip's emulator fed by the simulator), read through
  the one bounded read loop (``magnet.edge.readloop``): a failing bus backs off, is counted and marks the device
  unhealthy.
- ``ReplaySource``: a recording (``--replay FILE.csv``) at its own pace (``magnet.edge.replay``).
- ``MavlinkSource`` (``services.edge.mavlink_source``): MAVLink vehicles (``--mavlink URL``), devices as they appear.
- ``Ros2Source`` (``services.edge.ros2_source``): a ROS 2 robot's topics over rmw_zenoh (``--ros2``).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import smbus2
import zenoh

from magnet import wire
from magnet.drivers import open_sensor
from magnet.edge.readloop import ReadLoop
from magnet.edge.replay import Recording, paced_slices
from magnet.emulators import FaultInjector, emulator_for
from magnet.retry import READ_BACKOFF
from magnet.simulator import SensorStream, SimulatedDevices
from services.common.inputs import read_input
from services.common.inputs.input_options import InputOptions
from services.edge.mavlink_source import MavlinkSource
from services.edge.ros2_source import Ros2Source
from services.edge.settings import SIMULATOR_SENSOR, EdgeSettings, SourceKind
from services.edge.source import DeviceEvents, Source, Stop, stamp, ticked

TRUTH_KEYS = ("heading_deg", "pitch_deg", "roll_deg")
GYRO_COLUMNS = ("gx", "gy", "gz")
REPLAY_SENSOR = "replay"


def _truth(stream: SensorStream | None) -> dict[str, float]:
    truth = getattr(stream, "last_truth", None) or {}
    return {k: float(truth.get(k, 0.0)) for k in TRUTH_KEYS}


def _stream(settings: EdgeSettings) -> SensorStream:
    return settings.simulator.sensor_stream(settings.trajectory_samples, settings.rate_hz / settings.speedup)


class Unattached:
    """What the sources that need no session, cannot fail and hold nothing open share: ``attach``, ``status`` and
    ``close`` that do nothing."""

    def attach(self, session: zenoh.Session, events: DeviceEvents) -> None:
        """Nothing to declare, nothing to tell."""

    def status(self) -> dict[str, Any] | None:
        return None

    def close(self) -> None:
        """Nothing to release."""


class FleetSource(Unattached):
    """N simulated devices, one vectorized step per batch, every ``batch / rate`` seconds."""

    def __init__(self, settings: EdgeSettings) -> None:
        self.fleet = SimulatedDevices(
            n_devices=settings.devices,
            rate_hz=settings.rate_hz / settings.speedup,
            seed=settings.simulator.seed,
            noise_ut=settings.simulator.noise_ut,
            gyro=settings.gyro,
            **settings.simulator.place(),
        )
        self.ids = [f"{settings.device}-{i:03d}" for i in range(settings.devices)]
        self.settings = settings

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]:
        return ticked(self.take, self.settings.batch / self.settings.rate_hz, stop)

    def take(self, seq: int, end_ns: int, stop: Stop) -> list[wire.RawBatch]:
        """One batch of every device, the last sample at ``end_ns``."""
        step = self.fleet.step(self.settings.batch)
        t_ns = stamp(self.settings.batch, end_ns, int(1e9 / self.settings.rate_hz))
        return [
            wire.RawBatch(
                device,
                seq,
                SIMULATOR_SENSOR,
                t_ns,
                step.mag_ut[d],
                step.acc_ms2[d],
                {"heading_deg": step.heading_deg[d], "pitch_deg": step.pitch_deg[d], "roll_deg": step.roll_deg[d]},
                None if step.gyr_rads is None else step.gyr_rads[d],
            )
            for d, device in enumerate(self.ids)
        ]


class StreamSource(Unattached):
    """One simulated device read sample by sample from a ``SensorStream`` (no register emulation); a moving
    trajectory (multirotor, car, figure8, fast-tumble, a walk, boat, robot) also sends its gyroscope and its GNSS-like
    velocity."""

    def __init__(self, settings: EdgeSettings) -> None:
        self.stream = _stream(settings)
        self.settings = settings
        self.ids = [settings.device]

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]:
        return ticked(self.take, self.settings.batch / self.settings.rate_hz, stop)

    def take(self, seq: int, end_ns: int, stop: Stop) -> list[wire.RawBatch]:
        """One batch, the last sample at ``end_ns``."""
        n = self.settings.batch
        mag, acc, gyr, vel = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.full((n, 3), np.nan)
        truth = {k: np.empty(n) for k in TRUTH_KEYS}
        for i in range(n):
            mag[i], acc[i], gyr[i] = self.stream.measure_imu()
            for k, v in _truth(self.stream).items():
                truth[k][i] = v
            held = self.stream.last_truth.get("vel_ned_ms")
            if held is not None:
                vel[i] = held
        t_ns = stamp(n, end_ns, int(1e9 / self.settings.rate_hz))
        moving = self.settings.simulator.trajectory.moving
        return [
            wire.RawBatch(
                self.settings.device,
                seq,
                SIMULATOR_SENSOR,
                t_ns,
                mag,
                acc,
                truth,
                gyr if moving else None,
                vel_ned_ms=vel if moving and np.isfinite(vel).any() else None,
            )
        ]


def _rows(vectors: list[np.ndarray | None]) -> np.ndarray | None:
    """(N, 3) from N vectors of 3, or None when any is missing (the wire field is all or nothing per batch)."""
    return None if any(v is None for v in vectors) else np.array(vectors, dtype=float)


class ChipSource:
    """One chip through its driver and the bounded read loop; the edge's status hears each change of its health. A
    real chip paces itself (its reads wait for data), an emulated one is read every ``batch / rate`` seconds."""

    def __init__(self, settings: EdgeSettings) -> None:
        self.settings = settings
        self.ids = [settings.device]
        self.stream = _stream(settings) if settings.emulate else None
        self.opened = contextlib.ExitStack()
        options = {} if settings.address is None else {"address": settings.address}
        if settings.emulate:
            emulator = emulator_for(settings.sensor, self.stream)
            self.driver = open_sensor(settings.sensor, emulator, **options)
            if settings.emulate_faults:  # after set-up: the chip was found, then its bus fails
                emulator.faults = FaultInjector(probability=settings.emulate_faults, seed=settings.simulator.seed)
        else:
            with contextlib.ExitStack() as opening:  # the bus closes again when no chip answers on it
                bus = opening.enter_context(smbus2.SMBus(settings.bus))
                self.driver = open_sensor(settings.sensor, bus, **options)
                self.opened = opening.pop_all()
        self.loop = ReadLoop(self.driver.read, clock=time.monotonic, sleep=time.sleep, policy=READ_BACKOFF)

    def attach(self, session: zenoh.Session, events: DeviceEvents) -> None:
        self.loop.on_health = events.on_health

    def status(self) -> dict[str, Any]:
        return self.loop.health.as_dict()

    def close(self) -> None:
        self.opened.close()

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]:
        period_s = self.settings.batch / self.settings.rate_hz if self.settings.emulate else 0.0
        return ticked(self.take, period_s, stop)

    def take(self, seq: int, end_ns: int, stop: Stop) -> list[wire.RawBatch]:
        """Up to ``batch`` samples (fewer only when ``stop()`` turned true while the bus was failing), stamped from
        the wall clock when read."""
        mags, accs, gyrs, truths = [], [], [], []
        for _ in range(self.settings.batch):
            reading = self.loop.next(stop)
            if reading is None:
                break
            mags.append(np.asarray(reading.mag_ut, dtype=float))
            accs.append(reading.acc_ms2)
            gyrs.append(reading.gyr_rads)
            truths.append(_truth(self.stream))
        if not mags:
            return []
        truth = {k: np.array([t[k] for t in truths]) for k in TRUTH_KEYS} if self.stream is not None else None
        t_ns = stamp(len(mags), time.time_ns(), int(1e9 / self.settings.rate_hz))
        return [
            wire.RawBatch(
                self.settings.device,
                seq,
                self.settings.sensor,
                t_ns,
                np.array(mags),
                _rows(accs),
                truth,
                gyr_rads=_rows(gyrs),
            )
        ]


def read_recording(path: Path, topic: str | None = None, mag: int | None = None) -> Recording:
    """The recording in a ``magnet sample`` CSV: t_s (s), mx,my,mz (uT), optional ax,ay,az (m/s^2), gx,gy,gz
    (rad/s) and vn,ve,vd (m/s NED, empty or NaN where unknown), or a flight log or ROS 2 recording
    (``services.common.inputs``: ``mag`` the magnetometer instance of a flight log, ``topic`` the MagneticField topic
    of a bag); ValueError naming the file and what is wrong."""
    table = read_input(path, InputOptions(mag=mag, topic=topic))
    if "t_s" not in table.columns:
        raise ValueError(
            f"{path}: --replay needs a t_s column (seconds) to keep the recording's pace, as magnet sample writes it"
        )
    gyr = None
    if all(c in table.columns for c in GYRO_COLUMNS):
        gyr = np.column_stack([table.numeric(c) for c in GYRO_COLUMNS])
    try:
        return Recording(table.numeric("t_s"), table.mag, table.acc, gyr, table.vel_ned_ms())
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


class ReplaySource(Unattached):
    """A recording published at its own pace (scaled by ``--speed``), in batches of ``--batch``; then it ends."""

    def __init__(self, settings: EdgeSettings) -> None:
        if settings.replay is None:
            raise ValueError("a replay needs --replay FILE.csv")
        self.recording = read_recording(settings.replay, settings.mag_topic, settings.mag_instance)
        self.settings = settings
        self.ids = [settings.device]

    def batches(self, stop: Stop) -> Iterator[list[wire.RawBatch]]:
        """One list of one batch each time a batch is due; wire times keep the recording's intervals from now."""
        rec, device = self.recording, self.settings.device
        t_ns = rec.stamps_ns(time.time_ns())
        parts = paced_slices(
            rec, self.settings.batch, speed=self.settings.speed, clock=time.monotonic, sleep=time.sleep, stop=stop
        )
        for seq, part in enumerate(parts):
            yield [
                wire.RawBatch(
                    device,
                    seq,
                    REPLAY_SENSOR,
                    t_ns[part],
                    rec.mag_ut[part],
                    None if rec.acc_ms2 is None else rec.acc_ms2[part],
                    gyr_rads=None if rec.gyr_rads is None else rec.gyr_rads[part],
                    vel_ned_ms=None if rec.vel_ned_ms is None else rec.vel_ned_ms[part],
                )
            ]


#: the one dispatch table: the source each kind of settings names, by its constructor
SOURCES: dict[SourceKind, Callable[[EdgeSettings], Source]] = {
    SourceKind.MAVLINK: MavlinkSource,
    SourceKind.ROS2: Ros2Source,
    SourceKind.REPLAY: ReplaySource,
    SourceKind.FLEET: FleetSource,
    SourceKind.SIMULATOR: StreamSource,
    SourceKind.CHIP: ChipSource,
}


def make_source(settings: EdgeSettings) -> Source:
    """The source the settings name (``settings.source_kind``), opened; ValueError or OSError when it cannot be."""
    return SOURCES[settings.source_kind](settings)
