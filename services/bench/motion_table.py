"""``magnet bench motion``'s table: BROAD and the moving simulator (``services.bench.motion``), then the heading
uncertainty's honesty (``services.bench.motion_sigma``)."""

from __future__ import annotations

import time

from services.bench import motion
from services.bench.motion_sigma import sigma_lines


def run_motion_benchmark() -> str:
    """The benchmark's table as text (``magnet bench motion``)."""
    started = time.perf_counter()
    lines = [
        "heading RMS in motion (deg); BROAD: offset removed, movement samples with |pitch| < 60 deg",
        (
            "(BROAD: 'fused' on the raw field is vqf with its defaults; 'fit accepted/refused': after the product's "
            "ellipsoid, 'gyro fit': after its gyro-ellipsoid)"
        ),
        f"{'recording':<42}{'estimator':<34}{'RMS':>8}",
    ]
    for trial, estimator, rms in motion.broad_rows(calibrated=True):
        lines.append(f"{trial:<42}{estimator:<34}{rms:>8.3f}")
    settings = motion.SimulatorSettings()
    lines.append(
        f"moving simulator, {settings.seconds:g} s at {settings.rate_hz:g} Hz, against the true magnetic "
        f"heading (no offset removed), after {settings.settle_s:g} s, |pitch| < 60 deg"
    )
    for trial, estimator, rms in motion.simulator_rows(settings):
        lines.append(f"{trial:<42}{estimator:<34}{rms:>8.3f}")
    lines.extend(sigma_lines(settings))
    lines.append(f"benchmark time {time.perf_counter() - started:.1f} s")
    return "\n".join(lines)
