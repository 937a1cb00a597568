"""Where ``magnet edge``'s samples come from. Each source's ``batches(seq, end_ns, stop)`` returns the next
``RawBatch`` of every device it holds (end_ns: wall-clock ns of the batch's last sample); ``stats`` (a
``ReadStats``, or None for simulated sources that cannot fail) counts its reads.

- ``FleetSource``: N simulated devices, one vectorized step per batch.
- ``StreamSource``: one simulated device read sample by sample (no register emulation).
- ``ChipSource``: one chip through its driver (a real bus, or the chip's emulator fed by the simulator), read through
  the one bounded read loop (``magnet.readloop``): a failing bus backs off, is counted and marks the device unhealthy.
- ``ReplaySource``: a recording (``--replay FILE.csv``) at its own pace (``magnet.replay``); it paces itself, so it
  offers ``paced(stop)`` instead of ``batches``.
- ``MavlinkSource`` (``services.edge.mavlink_source``): MAVLink vehicles (``--mavlink URL``), devices as they appear.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import smbus2

from magnet import wire
from magnet.drivers import open_sensor
from magnet.emulators import FaultInjector, emulator_for
from magnet.readloop import Backoff, ReadLoop, ReadStats
from magnet.replay import Recording, paced_slices
from magnet.simulator import SimulatedDevices
from services.common.input_options import InputOptions
from services.common.inputs import read_input
from services.edge.settings import SIMULATOR_SENSOR, EdgeSettings

#: the edge's read loop: waits 10 ms, 20 ms, ... up to 1 s between failed reads; unhealthy after 3 in a row
EDGE_BACKOFF = Backoff(initial_s=0.01, max_s=1.0, unhealthy_after=3, poll_s=0.0005)
TRUTH_KEYS = ("heading_deg", "pitch_deg", "roll_deg")
GYRO_COLUMNS = ("gx", "gy", "gz")
REPLAY_SENSOR = "replay"


def stamp(n: int, end_ns: int, period_ns: int) -> np.ndarray:
    """(n,) int64 ns: n sample times ``period_ns`` apart ending at ``end_ns``."""
    return end_ns - period_ns * np.arange(n - 1, -1, -1, dtype=np.int64)


def _truth(stream: Any) -> dict[str, float]:
    truth = getattr(stream, "last_truth", None) or {}
    return {k: float(truth.get(k, 0.0)) for k in TRUTH_KEYS}


def _stream(settings: EdgeSettings) -> Any:
    return settings.simulator.sensor_stream(settings.trajectory_samples, settings.rate_hz / settings.speedup)


class FleetSource:
    """N simulated devices, one vectorized step per batch."""

    stats: ReadStats | None = None

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

    def batches(self, seq: int, end_ns: int, stop: Callable[[], bool]) -> list[wire.RawBatch]:
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


class StreamSource:
    """One simulated device read sample by sample from a ``SensorStream`` (no register emulation); a moving
    trajectory (multirotor, car, figure8, fast-tumble) also sends its gyroscope and its GNSS-like velocity."""

    stats: ReadStats | None = None

    def __init__(self, settings: EdgeSettings) -> None:
        self.stream = _stream(settings)
        self.settings = settings
        self.ids = [settings.device]

    def batches(self, seq: int, end_ns: int, stop: Callable[[], bool]) -> list[wire.RawBatch]:
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


def _open_bus(settings: EdgeSettings, stream: Any) -> Any:
    if settings.emulate:
        return emulator_for(settings.sensor, stream)
    return smbus2.SMBus(settings.bus)


def _rows(vectors: list[Any]) -> np.ndarray | None:
    """(N, 3) from N vectors of 3, or None when any is missing (the wire field is all or nothing per batch)."""
    return None if any(v is None for v in vectors) else np.array(vectors, dtype=float)


class ChipSource:
    """One chip through its driver and the bounded read loop; ``on_health(healthy, last_error)`` hears each change."""

    def __init__(self, settings: EdgeSettings, on_health: Callable[[bool, str], None] | None = None) -> None:
        self.settings = settings
        self.ids = [settings.device]
        self.stream = _stream(settings) if settings.emulate else None
        bus = _open_bus(settings, self.stream)
        options = {} if settings.address is None else {"address": settings.address}
        self.driver = open_sensor(settings.sensor, bus, **options)
        if settings.emulate_faults:  # after set-up: the chip was found, then its bus fails
            bus.faults = FaultInjector(probability=settings.emulate_faults, seed=settings.simulator.seed)
        self.loop = ReadLoop(
            self.driver.read, clock=time.monotonic, sleep=time.sleep, backoff=EDGE_BACKOFF, on_health=on_health
        )

    @property
    def stats(self) -> ReadStats:
        return self.loop.stats

    def batches(self, seq: int, end_ns: int, stop: Callable[[], bool]) -> list[wire.RawBatch]:
        """Up to ``batch`` samples (fewer only when ``stop()`` turned true while the bus was failing)."""
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


class ReplaySource:
    """A recording published at its own pace (scaled by ``--speed``), in batches of ``--batch``; then it ends."""

    stats: ReadStats | None = None

    def __init__(self, settings: EdgeSettings) -> None:
        if settings.replay is None:
            raise ValueError("a replay needs --replay FILE.csv")
        self.recording = read_recording(settings.replay, settings.mag_topic, settings.mag_instance)
        self.settings = settings
        self.ids = [settings.device]

    def paced(self, stop: Callable[[], bool]) -> Iterator[list[wire.RawBatch]]:
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


def make_source(settings: EdgeSettings, on_health: Callable[[bool, str], None] | None = None) -> Any:
    """The source the settings name (see the module docstring)."""
    if settings.mavlink is not None:
        from services.edge.mavlink_source import MavlinkSource

        return MavlinkSource(settings, on_health)
    if settings.replay is not None:
        return ReplaySource(settings)
    if settings.ros2.enabled:
        from services.edge.ros2_source import Ros2Source

        return Ros2Source(settings)
    if settings.devices:
        return FleetSource(settings)
    if settings.emulate and settings.sensor == SIMULATOR_SENSOR:
        return StreamSource(settings)
    return ChipSource(settings, on_health)
