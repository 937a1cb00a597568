"""A vehicle's velocity that goes stale for a while (its position messages late or lost: the edge attaches none older
than a second) must not upset the velocity-aided filter. Batches without any velocity were fed to vqf directly, ahead
of the samples the aided filter still held back for their acceleration (up to a second): their turns were skipped and
a tumbling vehicle's heading went 175 deg off for seconds (test_edge_mavlink's heading RMS 10.7 deg in a loaded CI
run, 83 deg when its vehicle stand-in was stopped for 1.5 s). The core stepped batch by batch as the compass runs."""

from __future__ import annotations

import numpy as np
import pytest
from compass_steps import NOW_NS, compass_core, heading_batches

from magnet import wire
from magnet.attitude.heading import angle_difference_deg
from magnet.earth.expected import Earth
from magnet.simulator import SensorErrors, SensorStream, SimulatorConfig

RATE_HZ, BATCH, SAMPLES, STALE_FROM = 50.0, 25, 1000, 400


def _tumble() -> tuple[Earth, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The simulator's place and a tumble there: field, specific force, rates (N, 3), true heading (N,) deg."""
    stream = SensorStream(SimulatorConfig("tumble", rate_hz=RATE_HZ, count=SAMPLES, errors=SensorErrors(), seed=0))
    rows = []
    for _ in range(SAMPLES):
        mag, acc, gyr = stream.measure_imu()
        rows.append((mag, acc, gyr, stream.last_truth["heading_deg"]))
    mag, acc, gyr, truth = (np.array([r[i] for r in rows]) for i in range(4))
    return Earth.of(stream.earth), mag, acc, gyr, truth


@pytest.mark.parametrize("stale", [0, BATCH, 75, 300])
def test_a_stale_velocity_between_batches_leaves_the_aided_heading_on_the_truth(stale: int) -> None:
    earth, mag, acc, gyr, truth = _tumble()
    vel = np.zeros((SAMPLES, 3))  # standing still, known at every sample...
    vel[STALE_FROM : STALE_FROM + stale] = np.nan  # ...but for these
    t_ns = NOW_NS + np.arange(SAMPLES, dtype=np.int64) * int(1e9 / RATE_HZ)
    core = compass_core(earth)
    headings = []
    for seq, lo in enumerate(range(0, SAMPLES, BATCH)):
        part = slice(lo, lo + BATCH)
        batch = wire.RawBatch(
            "v", seq, "sim", t_ns[part], mag[part], acc[part], gyr_rads=gyr[part], vel_ned_ms=vel[part]
        )
        (out,) = heading_batches(core, [batch], int(t_ns[part][-1]))
        headings.append(out.true_heading_deg)
    errors = np.abs(angle_difference_deg(np.concatenate(headings)[100:], truth[100:]))
    assert errors.max() < 1.0, f"worst {errors.max():.1f} deg at sample {100 + int(errors.argmax())}"
