"""The compass's own path in process, for ``magnet bench pipeline``: what one raw batch costs the compass loop's
thread in decode -> step -> encode, with no Zenoh, no other process and no queue (docs/cost.md, "The compass at
batch 100").

The same messages as the pipeline's load (``services.bench.ceiling``: the simulated fleet's bytes, stamped with
consecutive ``seq`` and times ``1 / rate`` apart, 4 distinct batches per device going round), a calibration in force
for every device, drains of ``DRAIN_MESSAGES`` messages as the service takes them when busy. Figures are CPU time of
this process (``time.process_time``: a busy machine disturbs it less than the wall clock), microseconds per raw batch,
the least of ``repeats`` runs after warm-up rounds (the filters and the per-device state made)."""

from __future__ import annotations

import dataclasses
import gc
import time

import numpy as np

from magnet import wire
from magnet.compass import CompassCore
from magnet.model import Calibration
from services.bench import ceiling

#: messages a drain takes when the compass is busy (``services.compass.service``: DRAIN_SAMPLES / batch at batch 100)
DRAIN_MESSAGES = 300
WARM_ROUNDS = 2
#: the calibration of every device, here and in the pipeline bench's compasses (``services.bench.pipeline._calibrate``)
CALIBRATION = Calibration(
    "ellipsoid",
    np.array([5.0, -3.0, 2.0]),
    np.array([[1.02, 0.01, 0.0], [0.01, 0.98, 0.005], [0.0, 0.005, 1.0]]),
    field_strength=50.0,
    accepted=True,
    reason="benchmark",
)


@dataclasses.dataclass(frozen=True)
class DrainCost:
    """CPU microseconds per raw batch of each stage (the least of the runs), and the batch's samples."""

    decode_us: float
    step_us: float
    encode_us: float
    batch: int

    @property
    def total_us(self) -> float:
        return self.decode_us + self.step_us + self.encode_us

    def line(self, devices: int, gyro: bool) -> str:
        return (
            f"compass in process ({devices} devices, {'gyroscopes' if gyro else 'no gyroscopes'}, batch {self.batch}, "
            f"drains of {DRAIN_MESSAGES}): decode {self.decode_us:.1f} + step {self.step_us:.1f} + encode "
            f"{self.encode_us:.1f} = {self.total_us:.1f} us a batch ({self.total_us / self.batch:.2f} us a sample: "
            f"{1e6 * self.batch / self.total_us:,.0f} samples/s for a whole core, before Zenoh)"
        )


def _messages(devices: int, batch: int, gyro: bool, rate_hz: float, rounds: int) -> list[tuple[str, bytes]]:
    """(key, payload) of ``rounds`` batches of every device, in the order the load sends them."""
    stampers = [[ceiling._Stamper(b) for b in step] for step in ceiling._fleet_batches(devices, batch, gyro, 4)]
    keys = [wire.key("magnet", ceiling.device_name(d), wire.Kind.RAW) for d in range(devices)]
    sample_ns = int(1e9 / rate_hz)
    offsets = sample_ns * np.arange(batch - 1, -1, -1, dtype=np.int64)
    start_ns = 1_780_000_000_000_000_000
    return [
        (keys[d], stampers[k % len(stampers)][d].stamp(k, start_ns + (k + 1) * batch * sample_ns - offsets))
        for k in range(rounds)
        for d in range(devices)
    ]


def _core(devices: int) -> CompassCore:
    core = CompassCore()
    for d in range(devices):
        device = ceiling.device_name(d)
        payload = wire.encode_calibration(device, CALIBRATION, 1)
        core.accept_calibration(payload, wire.key("magnet", device, wire.Kind.CALIBRATION), "magnet")
    return core


def _run(devices: int, batch: int, gyro: bool, rate_hz: float, rounds: int) -> DrainCost:
    core = _core(devices)
    items = _messages(devices, batch, gyro, rate_hz, rounds + WARM_ROUNDS)
    drains = [items[i : i + DRAIN_MESSAGES] for i in range(0, len(items), DRAIN_MESSAGES)]
    warm = WARM_ROUNDS * devices // DRAIN_MESSAGES
    spent = np.zeros(3)
    for index, drain in enumerate(drains):
        started = time.process_time()
        columns = core.decode(drain, "magnet")
        decoded = time.process_time()
        out = core.step(columns, int(columns.t_ns[-1]))
        stepped = time.process_time()
        core.encode(columns, out)
        if index >= warm:
            spent += (decoded - started, stepped - decoded, time.process_time() - stepped)
    decode_us, step_us, encode_us = (1e6 * spent / sum(len(d) for d in drains[warm:])).tolist()
    return DrainCost(decode_us, step_us, encode_us, batch)


def drain_cost(
    devices: int = 1000, batch: int = 100, gyro: bool = True, rate_hz: float = 1000.0, rounds: int = 4, repeats: int = 3
) -> DrainCost:
    """The least of ``repeats`` runs of ``rounds`` batches of every device (each stage's least on its own)."""
    gc_was = gc.get_threshold()
    gc.set_threshold(200_000, 20, 20)  # the compass service's (services.compass.service.GC_THRESHOLD)
    try:
        runs = [_run(devices, batch, gyro, rate_hz, rounds) for _ in range(repeats)]
    finally:
        gc.set_threshold(*gc_was)
    return DrainCost(
        min(r.decode_us for r in runs), min(r.step_us for r in runs), min(r.encode_us for r in runs), batch=batch
    )


if __name__ == "__main__":
    for with_gyro, rate in ((False, 1000.0), (True, 500.0)):
        print(drain_cost(gyro=with_gyro, rate_hz=rate).line(1000, with_gyro), flush=True)
