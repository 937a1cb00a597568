"""``magnet bench pipeline``: edge fleet process -> compass process -> a measuring subscriber (this process).

The compass runs with identity calibrations (no calibrator: the per-sample correction is computed all the same).
Each run publishes for ``seconds``; it reports samples/s in (published by the edge) and out (headings received),
loss, and the edge-to-heading latency (receive time minus the stamp of the batch's last sample) p50/p99. Then the
per-device rate is doubled until samples are lost or the edge cannot generate the rate, to find the highest rate
without loss. Everything on 127.0.0.1, explicit ports, no multicast scouting.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import threading
import time
from typing import Any

import msgpack
import numpy as np

from services.common.zenoh_session import free_ports, loopback_arguments

MAX_RATE_STEPS = 6
BISECT_STEPS = 2
DRAIN_S = 1.5          # after the edge stops, wait this long without new headings
STARTUP_TIMEOUT_S = 15


@dataclasses.dataclass(frozen=True)
class PipelineRun:
    devices: int
    rate_hz: float
    batch: int
    seconds: float
    samples_in: int
    samples_out: int
    generated_rate: float   # samples/s the edge achieved
    out_rate: float         # heading samples/s received
    latency_p50_ms: float
    latency_p99_ms: float

    @property
    def lost(self) -> int:
        return max(0, self.samples_in - self.samples_out)

    @property
    def loss_fraction(self) -> float:
        return self.lost / self.samples_in if self.samples_in else 0.0

    @property
    def target_rate(self) -> float:
        return self.devices * self.rate_hz

    def line(self) -> str:
        return (f"{self.devices} devices x {self.rate_hz:g} Hz, batch {self.batch}: target {self.target_rate:,.0f} "
                f"samples/s; in {self.generated_rate:,.0f}/s, out {self.out_rate:,.0f}/s, lost {self.lost} "
                f"({self.loss_fraction:.3%}), latency p50 {self.latency_p50_ms:.2f} ms, p99 {self.latency_p99_ms:.2f} ms")


class _Measurer:
    """Counts heading samples and their latency from a channel drained in its own thread."""

    def __init__(self, subscriber: Any) -> None:
        self.subscriber, self.samples = subscriber, 0
        self.latencies_ns: list[int] = []
        self.last_ns = time.monotonic_ns()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            sample = self.subscriber.try_recv()
            if sample is None:
                time.sleep(0.0002)
                continue
            now = time.time_ns()
            message = msgpack.unpackb(sample.payload.to_bytes())
            t_ns = message["t_ns"]
            self.samples += len(t_ns)
            self.latencies_ns.append(now - t_ns[-1])
            self.last_ns = time.monotonic_ns()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def _wait_ready(session: Any, key: str) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if any(reply.ok is not None for reply in session.get(key, timeout=1.0)):
            return
        time.sleep(0.2)
    raise OSError("the compass did not come up for the benchmark")


def run_once(devices: int, rate: float, batch: int, seconds: float) -> PipelineRun:
    import zenoh

    compass_port, edge_port, measure_port = free_ports(3)
    compass = subprocess.Popen([sys.executable, "-m", "services.cli", "compass", "--name", "bench-compass",
                                *loopback_arguments(compass_port)], stdin=subprocess.DEVNULL)
    edge = None
    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{measure_port}"]')
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{compass_port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    try:
        with zenoh.open(conf) as session:
            _wait_ready(session, "magnet/@status/bench-compass")
            measurer = _Measurer(session.declare_subscriber("magnet/*/heading",
                                                            zenoh.handlers.FifoChannel(1 << 20)))
            edge = subprocess.Popen([sys.executable, "-m", "services.cli", "edge", "--emulate", "--devices",
                                     str(devices), "--device", "b", "--rate", str(rate), "--batch", str(batch),
                                     "--duration", str(seconds), *loopback_arguments(edge_port, [compass_port])],
                                    stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True)
            out, _ = edge.communicate(timeout=seconds + 60)
            summary = json.loads(out.strip().splitlines()[-1])
            while (time.monotonic_ns() - measurer.last_ns) / 1e9 < DRAIN_S:
                time.sleep(0.1)
            measurer.stop()
    finally:
        for proc in (edge, compass):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=10)
    latencies = np.array(measurer.latencies_ns or [0]) / 1e6
    return PipelineRun(devices, rate, batch, seconds, summary["published_samples"], measurer.samples,
                       summary["published_samples"] / summary["seconds"], measurer.samples / summary["seconds"],
                       float(np.percentile(latencies, 50)), float(np.percentile(latencies, 99)))


def run_pipeline_benchmark(devices: int, rate: float, batch: int, seconds: float) -> None:
    """Print one line per run: the given rate, then doubled rates until loss, then BISECT_STEPS halvings of the gap
    between the best rate without loss and the first with loss; last, the highest rate without loss."""
    if devices < 1 or rate <= 0 or batch < 1 or seconds <= 0:
        raise ValueError("devices, rate, batch and seconds must all be positive")
    best: PipelineRun | None = None
    lossy: float | None = None
    current = float(rate)
    for _ in range(MAX_RATE_STEPS):
        result = _report(run_once(devices, current, batch, seconds))
        if result.lost:
            lossy = current
            break
        best = result
        if result.generated_rate < 0.9 * result.target_rate and seconds < 10 * batch / current:
            print(f"each device sends one batch every {batch / current:g} s: give --seconds of at least "
                  f"{10 * batch / current:g} for a fair rate", flush=True)
            break
        if result.generated_rate < 0.9 * result.target_rate:
            print(f"the edge process generates at most {result.generated_rate:,.0f} samples/s here: the limit is the "
                  f"generator, not the compass", flush=True)
            break
        current *= 2
    if best is not None and lossy is not None:
        best = _bisect(best, lossy, devices, batch, seconds)
    if best is None:
        print("loss already at the first rate: no rate without loss found", flush=True)
    else:
        print(f"highest rate without loss: {best.generated_rate:,.0f} samples/s ({best.devices} devices x "
              f"{best.rate_hz:g} Hz, batch {best.batch}), p99 latency {best.latency_p99_ms:.2f} ms", flush=True)


def _bisect(best: PipelineRun, lossy: float, devices: int, batch: int, seconds: float) -> PipelineRun:
    """BISECT_STEPS halvings of the gap between the best run without loss and the lowest rate with loss."""
    for _ in range(BISECT_STEPS):
        middle = (best.rate_hz + lossy) / 2
        result = _report(run_once(devices, middle, batch, seconds))
        if result.lost:
            lossy = middle
        else:
            best = result
    return best


def _report(result: PipelineRun) -> PipelineRun:
    print(result.line(), flush=True)
    return result
