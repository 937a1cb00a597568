"""``magnet bench pipeline --ros2``: what the compass's ROS 2 side costs. The same load twice at one rate, the compass
without and with ``--ros2`` (a MagneticField and an Imu per sample on rmw_zenoh's keys, diagnostics every second),
a ROS 2 subscriber counting in the measuring process; printed: both runs' lines, the compass's CPU seconds per
1,000 samples in each, the extra per ROS 2 message, and the ROS 2 messages received."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from services.bench.pipeline import PipelineRun


class _Counter:
    """Counts the ROS 2 messages of domain 0 (called from Zenoh's threads)."""

    def __init__(self) -> None:
        self.count, self.lock, self.subscriber = 0, threading.Lock(), None

    def attach(self, session: Any) -> None:
        self.subscriber = session.declare_subscriber("0/**", self._on)

    def _on(self, sample: Any) -> None:
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
