"""Issue 32: the edge's ROS 2 buffers are bounded by bytes, not only by count (100 kB frame ids made 334 MB of Imu
samples), and a MagneticField stamp that runs backwards is dropped and counted, not published silently."""

from __future__ import annotations

import numpy as np

from magnet.ros2 import messages
from magnet.ros2.pairing import MAX_PENDING_BYTES, SamplePairer, sample_bytes

BIG_FRAME = "f" * 100_000  # one string shared by every sample: the test holds 100 kB, the pairer counts each


def test_imu_samples_with_huge_frame_ids_are_bounded_by_bytes() -> None:
    pairer = SamplePairer(with_imu=True, batch=10)
    for k in range(400):  # 40 MB of frame ids, were each its own
        pairer.add_imu(messages.ImuSample(k * 1_000_000, BIG_FRAME, np.zeros(3), np.zeros(3)))
    held = len(pairer.imu)
    assert held * sample_bytes(pairer.imu[0]) <= MAX_PENDING_BYTES < (held + 1) * sample_bytes(pairer.imu[0])
    assert pairer.imu_bytes <= MAX_PENDING_BYTES and pairer.dropped == {"imu-backlog": 400 - held}


def test_field_samples_with_huge_frame_ids_are_bounded_by_bytes_and_freed_when_batched() -> None:
    pairer = SamplePairer(with_imu=False, batch=10)
    for k in range(400):
        pairer.add_mag(messages.MagSample(1 + k, BIG_FRAME, np.array([20e-6, 0, -40e-6])), now_s=0.0)
    assert pairer.mag_bytes <= MAX_PENDING_BYTES and pairer.dropped["mag-backlog"] > 200
    taken = sum(len(j.t_ns) for j in pairer.batches(now_s=1.0, flush=True))
    assert taken == 400 - pairer.dropped["mag-backlog"] and pairer.mag_bytes == 0


def test_a_field_stamp_that_runs_backwards_is_dropped_and_counted() -> None:
    pairer = SamplePairer(with_imu=False, batch=10)
    for t_ns in (1_000, 2_000, 1_500, 2_000, 3_000):
        pairer.add_mag(messages.MagSample(t_ns, "m", np.array([20e-6, 0, -40e-6])), now_s=0.0)
    (joined,) = pairer.batches(now_s=1.0, flush=True)
    assert joined.t_ns.tolist() == [1_000, 2_000, 3_000] and pairer.dropped == {"mag-backwards": 2}
