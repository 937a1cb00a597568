"""``magnet bench pipeline --ros2``: what the compass's ROS 2 side costs. The same load twice at one rate, the compass
without and with ``--ros2`` (a MagneticField and an Imu per sample on rmw_zenoh's keys, diagnostics every second),
a ROS 2 subscriber counting in the measuring process; printed: both runs' lines, the compass's CPU seconds per
1,000 samples in each, the extra per ROS 2 message, and the ROS 2 messages received."""

from __future__ import annotations

import argparse
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from services.bench.pipeline_run import PipelineRun

if TYPE_CHECKING:
    import zenoh


class _Counter:
    """Counts the ROS 2 messages of domain 0 (called from Zenoh's threads)."""

    def __init__(self) -> None:
        self.count, self.lock = 0, threading.Lock()

    def attach(self, session: zenoh.Session) -> zenoh.Subscriber[None]:
        """The counting subscriber on ``session``; the caller declares it in a ``with`` block."""
        return session.declare_subscriber("0/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.count += 1


def _per_thousand(run: PipelineRun) -> float:
    return 1000 * run.compass_cpu_s / max(run.samples_out, 1)


def compare_ros2(run: Callable[..., PipelineRun]) -> None:
    """``run(**options)``: one pipeline run at the chosen rate (``services.bench.pipeline.run_once``)."""
    plain = run()
    print("without ROS 2:", plain.line(), flush=True)
    counter = _Counter()
    ros = run(compass_args=("--ros2",), on_session=counter.attach)
    print("with --ros2:   ", ros.line(), flush=True)
    extra_s = ros.compass_cpu_s - plain.compass_cpu_s * ros.samples_out / max(plain.samples_out, 1)
    messages = 2 * ros.samples_out
    print(
        f"compass CPU per 1,000 samples: {_per_thousand(plain) * 1000:.1f} ms without ROS 2, "
        f"{_per_thousand(ros) * 1000:.1f} ms with (x{_per_thousand(ros) / max(_per_thousand(plain), 1e-9):.2f}); "
        f"about {1e6 * extra_s / max(messages, 1):.1f} us of compass CPU per ROS 2 message "
        f"({messages:,} MagneticField + Imu for {ros.samples_out:,} samples); "
        f"ROS 2 messages received by a subscriber: {counter.count:,}; load average {ros.load:.1f}",
        flush=True,
    )
    build_us, total_us = publish_cost()
    print(
        f"the ROS 2 side alone (this process, drains of 50 devices x 10 samples, a subscriber in the process): "
        f"{total_us:.1f} us CPU per message, of which {build_us:.1f} us building the CDR",
        flush=True,
    )


def _drain(devices: int = 50, samples: int = 10, rate_hz: float = 50.0) -> tuple[Any, Any, Any]:
    """A compass's drain: one batch of ``samples`` per device (simulated, with gyroscopes), computed; (columns,
    headings, the compass's core)."""
    import numpy as np

    from magnet import wire
    from magnet.compass import CompassCore
    from magnet.simulator import SimulatedDevices

    step = SimulatedDevices(devices, rate_hz=rate_hz, seed=1, gyro=True).step(samples)
    gyr = np.asarray(step.gyr_rads)
    t_ns = 1_700_000_000_000_000_000 + np.arange(samples, dtype=np.int64) * int(1e9 / rate_hz)
    batches = [
        wire.RawBatch(f"dev-{d:03d}", 0, "sim", t_ns, step.mag_ut[d], step.acc_ms2[d], gyr_rads=gyr[d])
        for d in range(devices)
    ]
    columns = wire.RawColumns.from_batches(batches)
    core = CompassCore()
    return columns, core.step(columns, int(t_ns[-1])), core


def publish_cost(repeats: int = 20) -> tuple[float, float]:
    """CPU us per ROS 2 message of the compass's ROS 2 side alone, in this process: (building the CDR, building
    and putting), for drains of 50 devices x 10 samples, on a loopback session with a subscriber."""
    import time

    import zenoh

    from services.common.ros2_options import Ros2Settings
    from services.common.zenoh_session import add_zenoh_arguments, build_config, free_ports, loopback_arguments
    from services.compass.ros2 import Ros2Compass, build_drain

    columns, out, core = _drain()
    messages = 2 * len(columns.t_ns) * repeats
    started = time.process_time()
    for _ in range(repeats):
        build_drain(columns, out, [0.0] * len(columns.devices))
    build = time.process_time() - started
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    args = parser.parse_args(loopback_arguments(free_ports(1)[0]))
    counter = _Counter()
    with zenoh.open(build_config(args)) as session, counter.attach(session):
        ros = Ros2Compass(session, Ros2Settings(True), "bench", 1000)
        ros.publish(columns, out, core)  # the publishers declared
        started = time.process_time()
        for _ in range(repeats):
            ros.publish(columns, out, core)
        total = time.process_time() - started
        ros.close()
    return 1e6 * build / messages, 1e6 * total / messages
