"""The gyroscope's bias about the vertical learnt from vqf's magnetic corrections in the unaided causal filter
(magnet.attitude.heading_bias, used by magnet.attitude.fusion.Fusion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from magnet.attitude import fusion, heading_bias
from magnet.attitude.heading_bias import HeadingBias, up_in_body, vertical_turn_rad, vqf_flags_count
from services.bench import field_runs as fr

TILT = math.radians(20.0)  # the body's attitude: tilted 20 deg about x, then turned about the vertical
UP = np.array([0.0, math.sin(TILT), math.cos(TILT)])


def _attitude(yaw_rad: float) -> np.ndarray:
    """vqf quaternion (4,) body -> ENU: a tilt of 20 deg about body x, then a turn ``yaw_rad`` about the vertical."""
    tilt = np.array([math.cos(TILT / 2), math.sin(TILT / 2), 0.0, 0.0])
    yaw = np.array([math.cos(yaw_rad / 2), 0.0, 0.0, math.sin(yaw_rad / 2)])
    w1, x1, y1, z1 = yaw
    w2, x2, y2, z2 = tilt
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


class _Piece:
    """Feeds a loop whole pieces while the body turns about the vertical at a given rate."""

    def __init__(self, loop: HeadingBias) -> None:
        self.loop, self.yaw = loop, 0.0

    def __call__(self, delta: float, rate_rads: float = 0.0, disturbed: bool = False, sigma: float = math.inf):
        self.yaw += rate_rads * self.loop.remaining() * self.loop.period_s
        self.loop.observe(self.loop.remaining(), disturbed)
        return self.loop.step(delta, _attitude(self.yaw), sigma)


def test_a_steady_drift_of_delta_becomes_bias_along_the_up_axis_once_settled():
    loop = HeadingBias(0.02, 2.0)  # pieces of 25 samples (0.5 s), T_i = 8 s, settles after 2 s
    assert loop.piece_samples == 25
    _piece = _Piece(loop)
    assert not _piece(0.0).any()  # the first value only sets the reference
    for k in range(1, 3):
        assert not _piece(0.01 * k).any()  # 2 s not fed yet
    np.testing.assert_allclose(_piece(0.03), -0.01 / 8.0 * UP)  # 2 s fed, delta grew 0.01 rad
    assert not _piece(0.06, disturbed=True).any()  # disturbed: not used, the reference moves on
    np.testing.assert_allclose(_piece(0.06 + 2 * math.pi - 0.01), 0.01 / 8.0 * UP)  # wraps
    learnt = math.radians(heading_bias.MIN_SIGMA_DPS) / 2.0  # vqf learnt the bias itself (at rest): kept as it is
    assert not _piece(0.06 + 2 * math.pi + 0.01, sigma=learnt).any()


def test_no_learning_while_turning_nor_for_a_while_after():
    loop = HeadingBias(0.02, 1.0)
    _piece = _Piece(loop)
    for _ in range(4):
        _piece(0.0)
    turn = math.radians(heading_bias.TURN_RATE_DPS) * 3.0  # over the last two pieces: 1.5 times the limit
    assert not _piece(0.1, rate_rads=turn).any()  # a corner: the tilt it causes moves delta
    pieces_after = round(heading_bias.AFTER_TURN_S / heading_bias.PIECE_S)
    for k in range(pieces_after):
        assert not _piece(0.1 + 0.01 * (k + 1)).any()
    assert _piece(0.2 + 0.01 * pieces_after).any()


def test_up_in_body_and_the_turn_about_the_vertical_at_a_tilted_attitude():
    np.testing.assert_allclose(up_in_body([1.0, 0.0, 0.0, 0.0]), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(up_in_body([0.0, 1.0, 0.0, 0.0]), [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(up_in_body(_attitude(1.0)), UP, atol=1e-12)  # a turn about the vertical keeps it
    assert vertical_turn_rad(_attitude(0.3), _attitude(-0.2)) == pytest.approx(-0.5)
    assert vertical_turn_rad(_attitude(3.0), _attitude(-3.0)) == pytest.approx(2 * math.pi - 6.0)  # wraps


def _walk(seed: int = 1) -> tuple[fr.SimulatedRun, np.ndarray]:
    """A phone in a pocket (a tuning seed) with its true field (plus the sensor's noise level)."""
    run = fr.field_run(fr.MOTIONS["walk-pocket"], seed, fr.FieldSettings())
    noise = np.random.default_rng(0).normal(0.0, 0.5, run.true_field_ut.shape)
    return run, run.true_field_ut + noise


def test_answers_do_not_depend_on_how_the_samples_are_cut_into_batches():
    run, field = _walk()
    whole = fusion.Fusion(0.02, heading_bias=True).update(run.gyr_rads, run.acc_ms2, field).quat_wxyz
    parts = fusion.Fusion(0.02, heading_bias=True)
    pieces = [
        parts.update(run.gyr_rads[s : s + 7], run.acc_ms2[s : s + 7], field[s : s + 7]).quat_wxyz
        for s in range(0, 2996, 7)
    ]
    np.testing.assert_allclose(np.vstack(pieces), whole[:2996], atol=1e-9)


def test_a_walking_phone_loses_its_standing_heading_offset():
    """Seed 1's gyroscope has 0.5 deg/s about the walker's vertical, which vqf never learns while walking: its heading
    lags by about bias x tauMag. With the loop the offset goes (measured 4.4 -> 1.8 deg abs after 25 s)."""
    run, field = _walk()
    truth, scored = fr.magnetic_truth(run), run.t_s >= 25.0
    errors = {}
    for on in (False, True):
        quat = fusion.Fusion(0.02, heading_bias=on).update(run.gyr_rads, run.acc_ms2, field).quat_wxyz
        errors[on] = fr.rms_deg(fr.heading_error_deg(quat, truth), scored, offset_removed=False)
    assert errors[True] < 0.6 * errors[False], errors


def test_vqf_s_flags_stop_the_loop_until_a_calibration_is_put_in_force():
    """Before any record (the raw field) vqf's flags count; after restart_magnetometer, while vqf has no reference
    yet (it waits for fast turns), they do not, and once it has one they count again."""
    filt = fusion.Fusion(0.02, heading_bias=True)
    assert vqf_flags_count(filt._recalibrated, filt._filter)
    filt.restart_magnetometer()
    assert filt._filter.getMagRefNorm() == 0.0 and not vqf_flags_count(filt._recalibrated, filt._filter)
    filt._filter.setMagRef(50.0, 1.1)
    assert vqf_flags_count(filt._recalibrated, filt._filter)
    filt.restart()
    assert vqf_flags_count(filt._recalibrated, filt._filter)
