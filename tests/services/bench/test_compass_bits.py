"""The compass's answers pinned to the bit on the pipeline bench's own drains (issue 28: the cost cuts must not move
them). ``CompassCore.step``'s outputs (headings, pitch, roll, field, flags, true headings, dips, quaternions, sigmas)
and the heading payloads of 12 devices over 1.6 s (800 samples each at 500 Hz with gyroscopes, past three of the turn
gate's 0.5 s blocks), in drains of 5 and of 12 messages, with and without gyroscopes, are hashed.

A cut of the compass's cost leaves these digests as they are. A change that means to change the answers (new maths,
new flags, another wire format) changes them: check that the new answers are the intended ones, then replace the
digest here with the one the failure prints, saying why in the commit."""

import hashlib

import numpy as np
import pytest

from services.bench import compass_drain

DEVICES, ROUNDS = 12, 8
PINNED = {
    (False, 5): "e3a56f04724bdd02929483470ffb96d87b885229d39e8d2f0a1bf2073490b150",
    (False, 12): "d7eb099e2f94b2f4c0008da8dcd99a33f31b779aa06171cca63de392c4d10c23",
    (True, 5): "cce5bef7ef0ec390550ffa5a60c9fa57d549b41ee7785def4917ed17d13653b1",
    (True, 12): "4222cb4dda8c6b7490471ad3555c3ecc05af17e6f4b659dc557de602a1bdea79",
}


def _digest(gyro: bool, drain_messages: int) -> str:
    core = compass_drain._core(DEVICES)
    items = compass_drain._messages(DEVICES, 100, gyro, 500.0 if gyro else 1000.0, ROUNDS)
    digest = hashlib.sha256()
    for start in range(0, len(items), drain_messages):
        columns = core.decode(items[start : start + drain_messages], "magnet")
        out = core.step(columns, int(columns.t_ns[-1]))
        h = out.headings
        for array in (h.heading_deg, h.pitch_deg, h.roll_deg, h.field_ut, h.flags, out.true_heading_deg, out.dip_deg,
                      out.quat_wxyz, out.heading_sigma_deg, out.tilt_sigma_deg):  # fmt: skip
            digest.update(b"-" if array is None else np.ascontiguousarray(array).tobytes())
        for payload in core.encode(columns, out):
            digest.update(payload)
        digest.update(repr((out.calibration_ids, out.declinations)).encode())
    assert not core.drops.counts
    return digest.hexdigest()


@pytest.mark.parametrize(("gyro", "drain_messages"), sorted(PINNED))
def test_the_compass_answers_the_bench_drains_bit_for_bit_as_pinned(gyro, drain_messages):
    got = _digest(gyro, drain_messages)
    assert got == PINNED[gyro, drain_messages], (
        f"the compass's outputs or payloads changed ({'gyroscopes' if gyro else 'no gyroscopes'}, drains of "
        f"{drain_messages}): a cost cut must leave them to the bit; an intended change of the answers replaces the "
        f"pinned digest with {got!r} (see the module docstring)"
    )
