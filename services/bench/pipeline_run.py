"""One run of ``magnet bench pipeline`` (``PipelineRun``): the load, what came out, the latency, the compass's CPU
time, and whether the compass kept up. Its own module so the pipeline (``services.bench.pipeline``) and its ROS 2
comparison (``services.bench.pipeline_ros2``) both import it without a circle."""

from __future__ import annotations

import dataclasses

#: a run keeps up when it loses nothing and its p99 edge-to-heading latency stays under this
MAX_P99_MS = 1000.0


@dataclasses.dataclass(frozen=True)
class PipelineRun:
    devices: int
    rate_hz: float
    batch: int
    seconds: float
    samples_in: int
    samples_out: int
    generated_rate: float  # samples/s the edge achieved
    out_rate: float  # heading samples/s received
    latency_p50_ms: float
    latency_p99_ms: float
    shards: int = 1
    ceiling_rate: float | None = None  # Zenoh's samples/s on the same payloads
    load: float = 0.0  # the machine's 1-minute load average at the end of the run (other work competes for the CPU)
    compass_cpu_s: float = 0.0  # CPU seconds (user + system) the compass process(es) used from the load's start

    @property
    def lost(self) -> int:
        return max(0, self.samples_in - self.samples_out)

    @property
    def kept_up(self) -> bool:
        return self.lost == 0 and self.latency_p99_ms <= MAX_P99_MS

    @property
    def loss_fraction(self) -> float:
        return self.lost / self.samples_in if self.samples_in else 0.0

    @property
    def target_rate(self) -> float:
        return self.devices * self.rate_hz

    def line(self) -> str:
        fraction = f" ({self.out_rate / self.ceiling_rate:.0%} of the Zenoh ceiling)" if self.ceiling_rate else ""
        compasses = "1 compass" if self.shards == 1 else f"{self.shards} compass shards"
        return (
            f"{self.devices} devices x {self.rate_hz:g} Hz, batch {self.batch}, {compasses}: target "
            f"{self.target_rate:,.0f} samples/s; in {self.generated_rate:,.0f}/s, out {self.out_rate:,.0f}/s"
            f"{fraction}, lost {self.lost} ({self.loss_fraction:.3%}), latency p50 {self.latency_p50_ms:.2f} ms, "
            f"p99 {self.latency_p99_ms:.2f} ms{'' if self.kept_up else ' (falls behind)'}; load average {self.load:.1f}"
            f"; compass CPU {self.compass_us_per_sample:.2f} us a sample ({self.compass_cpu_s / self.seconds:.2f} of "
            f"a core)"
        )

    @property
    def compass_us_per_sample(self) -> float:
        """The compass process(es)' CPU (all threads: Zenoh's too) over the samples the edge sent, us."""
        return 1e6 * self.compass_cpu_s / max(self.samples_in, 1)
