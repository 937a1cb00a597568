"""``magnet edge``: read one device (real I2C chip, emulated chip, or simulator) or a simulated fleet, and publish
batches of raw samples on ``<prefix>/<device>/raw`` (see ``magnet.wire``).

Sources:
- ``--sensor NAME --bus N [--address A]``: a real chip through smbus2, I2C errors retried with backoff.
- ``--sensor NAME --emulate``: the chip's register-level emulator (``magnet.emulators``) read through the same driver,
  its true field from a ``SensorStream`` (simulator) with the given hard iron, soft iron, noise and trajectory.
- ``--sensor sim --emulate``: the ``SensorStream`` directly, no register emulation.
- ``--emulate --devices N``: N simulated devices (``FleetSimulator``, each its own hard and soft iron) named
  ``<ID>-000`` ... from one process.

Emulated sources carry the simulator's true heading/pitch/roll in the message's ``truth``. On exit (``--duration`` or
a signal) it prints one JSON line: ``{"devices", "published_samples", "published_batches", "seconds", "read_errors"}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import time
from typing import Any, Callable, Iterator

import numpy as np

from magnet import wire
from services.common import sim_options
from services.common.zenoh_session import add_zenoh_arguments, open_session, stop_event

log = logging.getLogger("magnet.edge")

SIMULATOR_SENSOR = "sim"
MAX_BACKOFF_S = 2.0
FLEET_SLOTS = 20
MATCH_WAIT_S = 3.0   # at start, wait this long at most for a subscriber (so the first batches are not lost)
FLUSH_S = 0.3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="dev", help="device id (one key chunk); a fleet uses <ID>-000, ...")
    parser.add_argument("--sensor", default=SIMULATOR_SENSOR,
                        help="chip name (hmc5883l, qmc5883l, lsm303dlh, ak09918c+bma456) or 'sim' for the simulator alone")
    parser.add_argument("--bus", type=int, help="I2C bus number of a real chip (/dev/i2c-N)")
    parser.add_argument("--address", type=lambda s: int(s, 0), help="I2C address of a real chip (e.g. 0x1e)")
    parser.add_argument("--emulate", action="store_true", help="emulate the chip (or the fleet) instead of a bus")
    parser.add_argument("--devices", type=int, default=0, help="with --emulate: this many simulated devices")
    parser.add_argument("--rate", type=float, default=50.0, help="samples per second per device (default 50)")
    parser.add_argument("--batch", type=int, default=10, help="samples per message (default 10)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    sim_options.add_simulator_arguments(parser, seed=1, noise_ut=0.3)
    parser.add_argument("--trajectory-samples", type=int, default=3000,
                        help="samples per run of the simulated trajectory (default 3000)")
    parser.add_argument("--speedup", type=float, default=1.0,
                        help="simulated motion runs this many times faster than the wall clock (default 1)")
    add_zenoh_arguments(parser)


@dataclasses.dataclass(frozen=True)
class EdgeSettings:
    device: str
    sensor: str
    rate_hz: float
    batch: int
    duration_s: float | None

    def __post_init__(self) -> None:
        wire.validate_device_id(self.device)
        if not 0 < self.rate_hz <= 100_000:
            raise ValueError(f"--rate must be in (0, 100000] Hz, got {self.rate_hz}")
        if not 1 <= self.batch <= wire.MAX_BATCH_SAMPLES:
            raise ValueError(f"--batch must be 1..{wire.MAX_BATCH_SAMPLES}, got {self.batch}")


# ------------------------------------------------------------------------------------------------------- sources
# A source yields lists of RawBatch (one per device) each time it is called with the batch's wall-clock times.


def _sensor_stream(args: argparse.Namespace):
    return sim_options.sensor_stream(args, args.trajectory_samples, args.rate / _speedup(args))


def _speedup(args: argparse.Namespace) -> float:
    if not 0 < args.speedup <= 1000:
        raise ValueError(f"--speedup must be in (0, 1000], got {args.speedup}")
    return float(args.speedup)


def _truth(stream: Any) -> dict[str, float]:
    truth = getattr(stream, "last_truth", None) or {}
    return {k: float(truth.get(k, 0.0)) for k in ("heading_deg", "pitch_deg", "roll_deg")}


def _stamp(n: int, end_ns: int, period_ns: int) -> np.ndarray:
    return end_ns - period_ns * np.arange(n - 1, -1, -1, dtype=np.int64)


class FleetSource:
    """N simulated devices, one vectorized step per batch."""

    def __init__(self, args: argparse.Namespace, settings: EdgeSettings) -> None:
        from magnet.simulator import FleetSimulator

        place = sim_options.simulator_place(args)
        self.fleet = FleetSimulator(n_devices=args.devices, rate_hz=settings.rate_hz / _speedup(args),
                                    seed=args.seed, noise_ut=args.noise_ut, **place)
        self.ids = [f"{settings.device}-{i:03d}" for i in range(args.devices)]
        self.settings = settings

    def batches(self, seq: int, end_ns: int) -> list[wire.RawBatch]:
        step = self.fleet.step(self.settings.batch)
        t_ns = _stamp(self.settings.batch, end_ns, int(1e9 / self.settings.rate_hz))
        return [wire.RawBatch(device, seq, "sim", t_ns, step.mag_ut[d], step.acc_ms2[d],
                              {"heading_deg": step.heading_deg[d], "pitch_deg": step.pitch_deg[d],
                               "roll_deg": step.roll_deg[d]})
                for d, device in enumerate(self.ids)]


class StreamSource:
    """One simulated device read sample by sample from a ``SensorStream`` (no register emulation)."""

    def __init__(self, args: argparse.Namespace, settings: EdgeSettings) -> None:
        self.stream = _sensor_stream(args)
        self.settings = settings

    def batches(self, seq: int, end_ns: int) -> list[wire.RawBatch]:
        n = self.settings.batch
        mag, acc, truth = np.empty((n, 3)), np.empty((n, 3)), {k: np.empty(n) for k in _TRUTH}
        for i in range(n):
            mag[i], acc[i] = self.stream.measure()
            for k, v in _truth(self.stream).items():
                truth[k][i] = v
        t_ns = _stamp(n, end_ns, int(1e9 / self.settings.rate_hz))
        return [wire.RawBatch(self.settings.device, seq, SIMULATOR_SENSOR, t_ns, mag, acc, truth)]


_TRUTH = ("heading_deg", "pitch_deg", "roll_deg")


class ChipSource:
    """One chip through its driver: a real bus, or the chip's emulator fed by a ``SensorStream``.

    I2C errors (OSError) are retried with exponential backoff up to ``MAX_BACKOFF_S`` and counted, never fatal."""

    def __init__(self, args: argparse.Namespace, settings: EdgeSettings) -> None:
        from magnet.drivers import open_sensor

        self.settings = settings
        self.stream = None
        if args.emulate:
            from magnet.emulators import emulator_for

            self.stream = _sensor_stream(args)
            bus = emulator_for(settings.sensor, self.stream)
        else:
            if args.bus is None:
                raise ValueError("a real sensor needs --bus N (or --emulate)")
            import smbus2

            bus = smbus2.SMBus(args.bus)
        options = {} if args.address is None else {"address": args.address}
        self.driver = open_sensor(settings.sensor, bus, **options)
        self.read_errors = 0

    def read_one(self) -> tuple[np.ndarray, np.ndarray | None, dict[str, float]]:
        """One sample (mag uT (3,), acc m/s^2 (3,) or None, truth), waiting out not-ready and I2C errors."""
        backoff = 0.001
        while True:
            try:
                reading = self.driver.read()
            except OSError as exc:
                self.read_errors += 1
                if self.read_errors == 1 or self.read_errors % 100 == 0:
                    log.warning("I2C read failed (%d so far): %s; retrying", self.read_errors, exc)
                time.sleep(backoff)
                backoff = min(backoff * 2, MAX_BACKOFF_S)
                continue
            if reading.mag_ut is not None and reading.ready and not reading.overflow:
                acc = None if reading.acc_ms2 is None else np.asarray(reading.acc_ms2, dtype=float)
                return np.asarray(reading.mag_ut, dtype=float), acc, _truth(self.stream)
            time.sleep(0.0005)

    def batches(self, seq: int, end_ns: int) -> list[wire.RawBatch]:
        n = self.settings.batch
        samples = [self.read_one() for _ in range(n)]
        mag = np.array([s[0] for s in samples])
        acc = None if any(s[1] is None for s in samples) else np.array([s[1] for s in samples])
        truth = {k: np.array([s[2][k] for s in samples]) for k in _TRUTH} if self.stream is not None else None
        t_ns = _stamp(n, time.time_ns(), int(1e9 / self.settings.rate_hz))
        return [wire.RawBatch(self.settings.device, seq, self.settings.sensor, t_ns, mag, acc, truth)]


def make_source(args: argparse.Namespace, settings: EdgeSettings):
    if args.devices and not args.emulate:
        raise ValueError("--devices needs --emulate (a simulated fleet)")
    if args.devices:
        return FleetSource(args, settings)
    if args.emulate and settings.sensor == SIMULATOR_SENSOR:
        return StreamSource(args, settings)
    return ChipSource(args, settings)


# ---------------------------------------------------------------------------------------------------------- loop


def _ticks(period_s: float, stop: Callable[[], bool]) -> Iterator[int]:
    """Yields the wall-clock ns of each batch's end, paced at ``period_s``; never sleeps when behind."""
    start = time.monotonic()
    wall0 = time.time_ns()
    k = 0
    while not stop():
        k += 1
        target = start + k * period_s
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -1.0:  # far behind (overload): resynchronize instead of bursting
            start, k = time.monotonic() - k * period_s, k
        yield wall0 + int((time.monotonic() - start) * 1e9)


def _wait_for_subscribers(publisher: Any, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while not publisher.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.02)


def run(args: argparse.Namespace) -> int:
    settings = EdgeSettings(args.device, args.sensor, args.rate, args.batch, args.duration)
    source = make_source(args, settings)
    stop = stop_event()
    ids = getattr(source, "ids", [settings.device])
    published_samples = published_batches = 0
    import zenoh

    block = zenoh.CongestionControl.BLOCK  # raw samples wait for a congested link rather than vanish
    with open_session(args) as session:
        tokens = [session.liveliness().declare_token(wire.liveliness_key(args.prefix, "edge", f"{settings.device}"))]
        tokens += [session.liveliness().declare_token(wire.liveliness_key(args.prefix, "device", d)) for d in ids]
        keys = {d: wire.key(args.prefix, d, wire.Kind.RAW) for d in ids}
        # one declared publisher, only to wait for a subscriber; data goes by session.put (measured: a declared
        # publisher per device costs several times the CPU at 10,000 messages/s)
        first_publisher = session.declare_publisher(keys[ids[0]])
        log.info("edge: %d device(s), %s at %.1f Hz, batches of %d", len(ids), settings.sensor, settings.rate_hz,
                 settings.batch)
        _wait_for_subscribers(first_publisher, MATCH_WAIT_S)
        started = time.monotonic()
        deadline = None if settings.duration_s is None else started + settings.duration_s
        # a chip source paces itself through its reads; simulated sources are paced by the clock
        period = 0.0 if isinstance(source, ChipSource) and not args.emulate else settings.batch / settings.rate_hz

        def done() -> bool:
            return stop.is_set() or (deadline is not None and time.monotonic() >= deadline)

        # a fleet's devices are spread evenly over each period (real devices do not tick together), each slot
        # stamped when it goes out
        slots = min(len(ids), FLEET_SLOTS) if isinstance(source, FleetSource) else 1
        sample_ns = int(1e9 / settings.rate_hz)
        for seq, end_ns in enumerate(_ticks(period, done)):
            tick = time.monotonic()
            batches = source.batches(seq, end_ns)
            for slot in range(slots):
                if slot:
                    delay = tick + slot * period / slots - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    now_ns = time.time_ns()
                for batch in batches[slot::slots]:
                    if slot:
                        batch = dataclasses.replace(batch, t_ns=_stamp(len(batch), now_ns, sample_ns))
                    session.put(keys[batch.device], wire.encode_raw(batch), congestion_control=block)
                    published_samples += len(batch)
                    published_batches += 1
        seconds = time.monotonic() - started
        time.sleep(FLUSH_S)  # let the last batches leave before the session closes
        for token in tokens:
            token.undeclare()
    print(json.dumps({"devices": len(ids), "published_samples": published_samples,
                      "published_batches": published_batches, "seconds": round(seconds, 3),
                      "read_errors": getattr(source, "read_errors", 0)}), flush=True)
    return 0
