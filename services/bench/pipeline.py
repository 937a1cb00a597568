"""``magnet bench pipeline``: load process -> compass process(es) -> a measuring subscriber (this process).

The load is the edge's messages for a simulated fleet, simulated ahead and stamped and encoded per message as they
go out (``services.bench.ceiling.generate``): the fleet simulator itself costs as much CPU as the compass.

First Zenoh's own rate on the same payloads (``services.bench.ceiling``: a publisher process putting the edge's
messages as fast as it can, a subscriber here that only counts). Then the pipeline: the edge's simulated devices send
gyroscopes (fusion on in the compass; ``gyro=False`` for tilt only), the compass applies a calibration per device
(published by the benchmark before the load starts; no calibrator). Each run publishes for ``seconds``; it reports
samples/s in (published by the edge) and out (headings received), loss, the rate out as a fraction of the Zenoh
ceiling, and the edge-to-heading latency (receive time minus the stamp of the batch's last sample) p50/p99. The
per-device rate is doubled until the compass falls behind (samples lost, or p99 latency over ``MAX_P99_MS``: a queue
that grows for the whole run shows as latency before it shows as loss) or the edge cannot generate the rate, then
bisected, to find the highest rate the compass keeps up with. The rate out is the headings received over the time
they took to arrive (at least the run's): when the compass falls behind, its own rate. Last, the first rate it fell
behind at (or the highest tried) again with ``shards`` compass
processes (``--shard K/N``) against 1. Everything on 127.0.0.1, explicit ports, no multicast scouting.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack
import numpy as np

from magnet import wire
from services.bench import ceiling
from services.bench.pipeline_run import MAX_P99_MS, PipelineRun
from services.common.zenoh_session import free_ports, loopback_arguments

if TYPE_CHECKING:
    import zenoh

MAX_RATE_STEPS = 6
BISECT_STEPS = 2
DRAIN_S = 1.5  # after the edge stops, wait this long without new headings
STARTUP_TIMEOUT_S = 15


class _Measurer:
    """Counts heading samples and their latency from a channel drained in its own thread."""

    def __init__(self, subscriber: zenoh.Subscriber[zenoh.Handler[zenoh.Sample]]) -> None:
        self.subscriber, self.samples = subscriber, 0
        self.latencies_ns: list[int] = []
        self.first_ns: int | None = None
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
            count, last_ns = heading_times(sample.payload.to_bytes())
            self.samples += count
            self.latencies_ns.append(now - last_ns)
            self.last_ns = time.monotonic_ns()
            if self.first_ns is None:
                self.first_ns = self.last_ns

    @property
    def span_s(self) -> float:
        """Seconds from the first heading received to the last."""
        return 0.0 if self.first_ns is None else (self.last_ns - self.first_ns) / 1e9

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def heading_times(payload: bytes) -> tuple[int, int]:
    """(samples, the last sample's t_ns) of one heading message: in v 2 read from its ``t_ns`` entry alone, the
    entries before it skipped unbuilt (4.9 us a message of 100 samples against 13.9 for ``wire.unpack``: at
    10,000 messages/s the measurer, beside the compass on the same 2 cores, took 0.23 of a core); anything else
    through ``wire.unpack``."""
    unpacker = msgpack.Unpacker()
    unpacker.feed(payload)
    with contextlib.suppress(Exception):  # not the v 2 layout read here: the whole message below
        for _ in range(unpacker.read_map_header()):
            if unpacker.unpack() != "t_ns":
                unpacker.skip()
                continue
            t_ns = unpacker.unpack()
            if isinstance(t_ns, dict) and t_ns.get("dtype") == "<i8" and len(t_ns.get("data", b"")) >= 8:
                data = t_ns["data"]
                return len(data) // 8, int.from_bytes(data[-8:], "little", signed=True)
            break
    times = wire.unpack(payload, wire.HEADING_LIMITS)["t_ns"]
    if isinstance(times, dict):  # v 2: <i8 bytes
        times = np.frombuffer(times["data"], dtype="<i8")
    return len(times), int(times[-1])


def _wait_ready(session: zenoh.Session, key: str) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if any(reply.ok is not None for reply in session.get(key, timeout=1.0)):
            return
        time.sleep(0.2)
    raise OSError("the compass did not come up for the benchmark")


def _calibrate(session: zenoh.Session, devices: int, shards: int) -> None:
    """Publish one accepted calibration per device (hard and soft iron, as a calibrator would) and wait until the
    compasses hold them all: the benchmark's compasses apply real calibrations, as in service."""
    from services.bench.compass_drain import CALIBRATION

    for d in range(devices):
        device = ceiling.device_name(d)
        session.put(wire.key("magnet", device, wire.Kind.CALIBRATION), wire.encode_calibration(device, CALIBRATION, 1))
    deadline = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        held = 0
        for k in range(shards):
            for reply in session.get(f"magnet/@status/bench-compass-{k}", timeout=1.0):
                if reply.ok is not None:
                    held += int(wire.unpack(reply.ok.payload.to_bytes())["calibrations"])
        if held >= devices:
            return
        time.sleep(0.2)
    raise OSError("the compasses did not take the benchmark's calibrations")


def _session_config(listen_port: int, connect_ports: list[int]) -> zenoh.Config:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{listen_port}"]))
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in connect_ports]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def run_once(
    devices: int,
    rate: float,
    batch: int,
    seconds: float,
    shards: int = 1,
    gyro: bool = True,
    ceiling_rate: float | None = None,
    compass_args: tuple[str, ...] = (),
    on_session: Callable[[zenoh.Session], contextlib.AbstractContextManager[object]] | None = None,
) -> PipelineRun:
    """One run: ``shards`` compass processes (``--shard K/N``, plus ``compass_args``), the edge connected to each,
    the measurer too (``on_session`` is given its session before the load starts: what it declares, in a context
    manager, stays declared until the session closes)."""
    import zenoh

    *compass_ports, measure_port = free_ports(shards + 1)
    compasses = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "services.cli",
                "compass",
                "--name",
                f"bench-compass-{k}",
                "--shard",
                f"{k}/{shards}",
                *loopback_arguments(port),
                *compass_args,
            ],
            stdin=subprocess.DEVNULL,
        )
        for k, port in enumerate(compass_ports)
    ]
    edge: subprocess.Popen[Any] | None = None
    try:
        with contextlib.ExitStack() as declared:
            session = declared.enter_context(zenoh.open(_session_config(measure_port, compass_ports)))
            for k in range(shards):
                _wait_ready(session, f"magnet/@status/bench-compass-{k}")
            _calibrate(session, devices, shards)
            headings = session.declare_subscriber("magnet/*/heading", zenoh.handlers.FifoChannel(1 << 20))
            measurer = _Measurer(declared.enter_context(headings))
            if on_session is not None:
                declared.enter_context(on_session(session))
            cpu_before_s = sum(_cpu_s(c.pid) for c in compasses)
            edge = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "services.bench.ceiling",
                    "generate",
                    ",".join(map(str, compass_ports)),
                    str(devices),
                    str(rate),
                    str(batch),
                    str(seconds),
                    str(int(gyro)),
                ],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                text=True,
            )
            out, _ = edge.communicate(timeout=seconds + 60)
            summary = json.loads(out.strip().splitlines()[-1])
            while (time.monotonic_ns() - measurer.last_ns) / 1e9 < DRAIN_S:
                time.sleep(0.1)
            measurer.stop()
            cpu_s = sum(_cpu_s(c.pid) for c in compasses) - cpu_before_s
    finally:
        procs: list[subprocess.Popen[Any] | None] = [edge, *compasses]
        for proc in procs:
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=10)
    latencies = np.array(measurer.latencies_ns or [0]) / 1e6
    return PipelineRun(
        devices,
        rate,
        batch,
        seconds,
        summary["published_samples"],
        measurer.samples,
        summary["published_samples"] / summary["seconds"],
        measurer.samples / max(summary["seconds"], measurer.span_s),
        float(np.percentile(latencies, 50)),
        float(np.percentile(latencies, 99)),
        shards,
        ceiling_rate,
        os.getloadavg()[0],
        cpu_s,
    )


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a running process has used (Linux /proc; 0 elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def run_pipeline_benchmark(
    devices: int, rate: float, batch: int, seconds: float, shards: int = 2, gyro: bool = True, ros2: bool = False
) -> None:
    """Print the Zenoh ceiling on the same payloads, then one line per run: the given rate, then doubled rates until
    the compass falls behind, then BISECT_STEPS halvings of the gap between the best rate kept up with and the first
    fallen behind at; the highest rate kept up with; last, the first rate fallen behind at (or the highest tried)
    with ``shards`` compasses."""
    if devices < 1 or rate <= 0 or batch < 1 or seconds <= 0 or shards < 1:
        raise ValueError("devices, rate, batch, seconds and shards must all be positive")
    if ros2:  # only the cost of the ROS 2 side, at this rate (services.bench.pipeline_ros2)
        from services.bench.pipeline_ros2 import compare_ros2

        compare_ros2(functools.partial(run_once, devices, rate, batch, seconds, gyro=gyro))
        return
    from services.bench.compass_drain import drain_cost

    print(drain_cost(devices, batch, gyro, rate).line(devices, gyro), flush=True)
    top = ceiling.measure(devices, batch, seconds, gyro)
    print(top.line(), flush=True)
    run = functools.partial(run_once, devices, batch=batch, seconds=seconds, gyro=gyro, ceiling_rate=top.sample_rate)
    best: PipelineRun | None = None
    lossy: float | None = None
    current, last = float(rate), float(rate)
    for _ in range(MAX_RATE_STEPS):
        result = _report(run(current))
        last = current
        if not result.kept_up:
            lossy = current
            break
        best = result
        if _generator_limited(result, seconds, batch, current):
            break
        current *= 2
    if best is not None and lossy is not None:
        best = _bisect(best, lossy, run)
    if best is None:
        print("behind already at the first rate: no rate kept up with", flush=True)
    else:
        print(
            f"highest rate kept up with (no loss, p99 latency <= {MAX_P99_MS:g} ms): {best.generated_rate:,.0f} "
            f"samples/s ({best.devices} devices x {best.rate_hz:g} Hz, batch {best.batch}), "
            f"{best.generated_rate / top.sample_rate:.0%} of the Zenoh ceiling, p99 latency {best.latency_p99_ms:.2f} "
            f"ms; load average {best.load:.1f}",
            flush=True,
        )
    if shards > 1:
        _compare_shards(run, lossy or last, shards)


def _generator_limited(result: PipelineRun, seconds: float, batch: int, current: float) -> bool:
    """Whether the edge could not generate the rate (said why); the search then stops."""
    if result.generated_rate >= 0.9 * result.target_rate:
        return False
    if seconds < 10 * batch / current:
        print(
            f"each device sends one batch every {batch / current:g} s: give --seconds of at least "
            f"{10 * batch / current:g} for a fair rate",
            flush=True,
        )
    else:
        print(
            f"the edge process generates at most {result.generated_rate:,.0f} samples/s here: the limit is the "
            f"generator, not the compass",
            flush=True,
        )
    return True


def _compare_shards(run: Callable[..., PipelineRun], rate: float, shards: int) -> None:
    one = _report(run(rate))
    many = _report(run(rate, shards=shards))
    print(
        f"{shards} compass shards against 1 at {one.target_rate:,.0f} samples/s: out {many.out_rate:,.0f}/s "
        f"against {one.out_rate:,.0f}/s (x{many.out_rate / max(one.out_rate, 1):.2f}), lost {many.loss_fraction:.1%} "
        f"against {one.loss_fraction:.1%}",
        flush=True,
    )


def _bisect(best: PipelineRun, lossy: float, run: Callable[..., PipelineRun]) -> PipelineRun:
    """BISECT_STEPS halvings of the gap between the best run kept up with and the lowest rate fallen behind at."""
    for _ in range(BISECT_STEPS):
        middle = (best.rate_hz + lossy) / 2
        result = _report(run(middle))
        if not result.kept_up:
            lossy = middle
        else:
            best = result
    return best


def _report(result: PipelineRun) -> PipelineRun:
    print(result.line(), flush=True)
    return result
