"""The gyroscope's bias about the vertical from the field's heading drift (magnet.attitude.drift_bias)."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
import vqf

from magnet.attitude import causal_drift as cd
from magnet.attitude import drift_bias as vb
from magnet.attitude import fusion
from magnet.attitude.causal_drift import note_batch, take_drift
from services.bench import field_runs as fr


def _drift_case(bias_dps: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """A walker-like up axis (mostly body z, swaying) over 90 s at 10 Hz, and the field's angle drifting by the
    bias about it, with 2 deg of tilt errors correlated over 2 s and an offset."""
    rng = np.random.default_rng(seed)
    period = 0.1
    t = np.arange(900) * period
    up = np.column_stack([0.2 * np.sin(2 * np.pi * t / 7.0), 0.1 * np.cos(2 * np.pi * t / 3.0), np.ones_like(t)])
    up /= np.linalg.norm(up, axis=1)[:, None]
    bias = np.array([0.1, -0.2, 1.0]) * math.radians(bias_dps)
    drift = np.cumsum(up @ bias) * period
    errors = np.convolve(rng.standard_normal(len(t)), np.ones(20) / math.sqrt(20), mode="same") * math.radians(2.0)
    return math.remainder(1.0, math.tau) + drift + errors, up, period


def test_fit_drift_finds_the_bias_about_the_up_axis() -> None:
    for bias_dps in (0.4, -0.25, 0.0):
        angle, up, period = _drift_case(bias_dps)
        found = vb.fit_drift(np.angle(np.exp(1j * angle)), up, period)  # wrapped, as atan2 gives it
        assert found is not None
        expected = math.radians(bias_dps) * float(found.up @ np.array([0.1, -0.2, 1.0]))
        assert abs(found.along_up_rads - expected) < math.radians(0.03)
        assert found.sigma_rads < math.radians(0.05)
        assert np.allclose(found.bias_rads, found.along_up_rads * found.up)


def test_fit_drift_resists_a_disturbed_stretch_and_needs_enough_samples() -> None:
    angle, up, period = _drift_case(0.3, seed=1)
    angle[300:330] += math.radians(40.0)  # a steel door passed: 3 s of the field turned
    found = vb.fit_drift(angle, up, period)
    assert found is not None
    assert abs(found.along_up_rads - math.radians(0.3) * float(found.up @ np.array([0.1, -0.2, 1.0]))) < math.radians(
        0.05
    )
    short = angle.copy()
    short[int(vb.MIN_SPAN_S / period) - 5 :] = np.nan
    assert vb.fit_drift(short, up, period) is None


def test_a_device_that_rested_keeps_vqfs_own_bias() -> None:
    period = 0.02
    count = 1500
    gyr = np.tile([0.0, 0.0, math.radians(0.3)], (count, 1))  # still, with a bias about the vertical
    acc = np.tile([0.0, 0.0, 9.81], (count, 1))
    field = np.tile([20.0, 0.0, -45.0], (count, 1))
    first = vqf.offlineVQF(gyr, acc, field, period)
    out_gyr, params, found = vb.offline_correction(gyr, field, period, {}, first)
    assert found == [] and params == {} and out_gyr is gyr


def test_offline_heading_of_a_walk_is_better_with_the_bias_found() -> None:
    """A simulated phone in a pocket (tuning seed 1, 60 s): the offline heading after the constant offset, with the
    simulator's true calibration, with and without the bias about the vertical found from the field."""
    settings = fr.FieldSettings(seconds=60.0)
    run = fr.field_run(fr.MOTIONS["walk-pocket"], 1, settings)
    field = run.errors.true_calibration(float(run.earth.total_ut)).apply(run.mag_ut)
    settled = run.t_s >= settings.settle_s
    truth = fr.magnetic_truth(run)
    figures = {}
    for on in (False, True):
        fused = fusion.fuse_offline(run.gyr_rads, run.acc_ms2, field, 1.0 / settings.rate_hz, vertical_bias=on)
        figures[on] = fr.rms_deg(fr.heading_error_deg(fused.quat_wxyz, truth), settled)
    assert figures[True] < 0.8 * figures[False], figures


def test_a_long_log_gets_a_bias_per_part() -> None:
    """A device turning about its vertical (level, 25 Hz, never still) for 700 s whose bias about the vertical steps
    from 0.3 to -0.2 deg/s half-way: three parts, each with its own bias, the first and last within 0.03 deg/s."""
    period = 0.04
    t = np.arange(int(700.0 / period)) * period
    rate = np.radians(15.0 + 5.0 * np.sin(2 * np.pi * t / 40.0))  # true turn rate about the vertical (vqf's z up)
    yaw = np.cumsum(rate) * period
    bias = np.where(t < 350.0, math.radians(0.3), math.radians(-0.2))
    gyr = np.column_stack([np.zeros_like(t), np.zeros_like(t), rate + bias])
    acc = np.tile([0.0, 0.0, 9.81], (len(t), 1))
    # the Earth's field (north 20, up -45 uT) in body axes of a level device turned by yaw about z (ENU, FLU)
    field = np.column_stack([20.0 * np.sin(yaw), 20.0 * np.cos(yaw), np.full_like(t, -45.0)])
    first = vqf.offlineVQF(gyr, acc, field, period)
    out_gyr, params, found = vb.offline_correction(gyr, field, period, {}, first, lengthen=False)
    assert params == {} and len(found) == 3
    assert abs(found[0].along_up_rads - math.radians(0.3)) < math.radians(0.03)
    assert abs(found[2].along_up_rads + math.radians(0.2)) < math.radians(0.03)
    assert np.allclose(out_gyr[-1], gyr[-1] - found[2].bias_rads)


def test_a_whole_turn_of_the_field_passing_an_object_leaves_no_step() -> None:
    """3 s in which a passing object turns the field's angle through a whole turn (as a 55 uT steel door does): the
    drift before and after it stays one line, and the bias is found as without the object."""
    angle, up, period = _drift_case(0.3, seed=2)
    clean = vb.fit_drift(angle, up, period)
    spun = angle.copy()
    spun[400:430] -= np.linspace(0.0, 2.0 * np.pi, 30)  # the angle turned once, back where it was after
    found = vb.fit_drift(np.angle(np.exp(1j * spun)), up, period)
    assert clean is not None and found is not None
    assert abs(found.along_up_rads - clean.along_up_rads) < math.radians(0.02)
    assert found.residual_rad < math.radians(5.0)


def test_fit_drift_with_steps_is_the_plain_fit_when_they_are_even() -> None:
    angle, up, period = _drift_case(0.3, seed=2)
    plain = vb.fit_drift(angle, up, period)
    stepped = vb.fit_drift(angle, up, period, np.full(len(angle), period))
    assert plain is not None and stepped is not None
    assert np.allclose(plain.bias_rads, stepped.bias_rads) and math.isclose(plain.sigma_rads, stepped.sigma_rads)


class _Filter:
    """What ``CausalDrift`` asks of vqf: its bias estimate (3,) rad/s and that estimate's one-sigma bound."""

    def __init__(self, sigma_dps: float = 0.5) -> None:
        self.bias = np.zeros(3)
        self.sigma = math.radians(sigma_dps)

    def getBiasEstimate(self) -> tuple[np.ndarray, float]:  # noqa: N802 (vqf's name)
        return self.bias.copy(), self.sigma

    def setBiasEstimate(self, bias: np.ndarray) -> None:  # noqa: N802
        self.bias = np.asarray(bias, dtype=float)


def _turning_history(bias_dps: float, seconds: float = 16.0) -> tuple[cd.CausalDrift, np.ndarray]:
    """A level device turning about the vertical, one history row per 0.5 s: vqf's 6D heading drifting at the
    bias, the raw field the Earth's turned into the body plus a hard iron (returned)."""
    drift = cd.CausalDrift(_Filter())
    earth = np.array([0.0, 19.0, -46.0])  # ENU: north and down
    iron = np.array([150.0, -80.0, 300.0])
    rng = np.random.default_rng(3)
    for t in np.arange(0.5, seconds + 0.5, 0.5):
        heading = 1.2 * math.sin(t / 3.0)
        estimate = heading + math.radians(bias_dps) * t + math.radians(1.0) * rng.standard_normal()
        quat = np.array([math.cos(estimate / 2), 0.0, 0.0, math.sin(estimate / 2)])  # body -> ENU about up
        turn = np.array(
            [[math.cos(heading), -math.sin(heading), 0], [math.sin(heading), math.cos(heading), 0], [0, 0, 1]]
        )
        drift.note(float(t), turn.T @ earth + iron, np.zeros(3), quat)
    return drift, iron


def test_causal_drift_takes_the_bias_from_the_history_before_a_record() -> None:
    drift, iron = _turning_history(0.4, seconds=30.0)
    filter_ = drift.filter
    assert drift.from_history(lambda raw, gyr: raw - iron)
    assert abs(filter_.bias[2] - math.radians(0.4)) < math.radians(0.05)
    assert np.allclose(filter_.bias[:2], 0.0, atol=1e-9)  # about the up axis only
    assert drift.history == []  # integrated with the old bias: not fitted again


def test_causal_drift_leaves_a_bias_that_vqf_learnt_at_rest_or_a_short_history() -> None:
    drift, iron = _turning_history(0.4)
    rested = drift.filter = _Filter(sigma_dps=0.1)
    assert not drift.from_history(lambda raw, gyr: raw - iron)
    assert np.all(rested.bias == 0.0)
    short, iron = _turning_history(0.4, seconds=5.0)
    assert not short.from_history(lambda raw, gyr: raw - iron)
    drift, iron = _turning_history(0.4)  # the raw field left uncorrected: the hard iron turns with the body
    assert not drift.from_history(lambda raw, gyr: raw)


def test_the_compass_filter_takes_the_bias_as_a_record_comes() -> None:
    """``Fusion`` fed a level device turning about the vertical (FRD, gyroscope with a bias of 0.4 deg/s about its z
    axis), the raw field noted per batch: the record's correction hands vqf the bias about the vertical."""
    period, count = 0.02, 1000
    t = np.arange(count) * period
    rate = 1.2 * np.cos(t / 3.0) / 3.0  # yaw rate (rad/s) of heading 1.2 sin(t / 3)
    heading = 1.2 * np.sin(t / 3.0)
    gyr = np.column_stack([np.zeros(count), np.zeros(count), rate + math.radians(0.4)])
    acc = np.tile([0.0, 0.0, -9.81], (count, 1))  # FRD specific force of a level device
    earth = np.array([19.0, 0.0, 46.0])  # NED: north and down
    iron = np.array([150.0, -80.0, 300.0])
    body = np.column_stack([np.cos(heading) * earth[0], -np.sin(heading) * earth[0], np.full(count, earth[2])])
    raw = body + iron
    filter_ = fusion.Fusion(period)
    state = types.SimpleNamespace(filter=filter_, drift=None)  # what the compass keeps per device
    drain = types.SimpleNamespace(raw_source=(raw, None), inputs=(fusion.to_vqf_frame(gyr),))
    for start in range(0, count, 25):
        filter_.update(gyr[start : start + 25], acc[start : start + 25])
        note_batch(state, drain, start + 24)
    before = np.asarray(filter_._filter.getBiasEstimate()[0])
    filter_.restart_magnetometer()
    take_drift(state, lambda raw_vqf, gyr_vqf: raw_vqf - fusion.to_vqf_frame(iron))
    after = np.asarray(filter_._filter.getBiasEstimate()[0])
    # vqf's frame is z up: a bias about FRD z is -0.4 deg/s about its z
    assert abs(math.degrees(after[2]) + 0.4) < 0.05 < abs(math.degrees(before[2]) + 0.4)
    assert state.loop is not None  # and from the record on the bias loop learns what is left


def test_the_bias_loop_starts_with_a_record_and_learns_once_a_batch() -> None:
    """``take_drift`` starts the bias loop (``causal_drift.HEADING_LOOP``) on a filter without velocity aiding once a
    record's correction comes (not without one, nor where the filter is aided), and ``note_loop`` steps it once a
    fused batch: a level device turning at 10 deg/s (no rest, no turn of a corner) with a bias of 0.4 deg/s about
    the vertical, the true field in force, gets most of the bias into vqf's estimate within 90 s."""
    period, count = 0.02, 4500
    t = np.arange(count) * period
    rate = np.full(count, math.radians(10.0))
    heading = rate * t
    gyr = np.column_stack([np.zeros(count), np.zeros(count), rate + math.radians(0.4)])
    acc = np.tile([0.0, 0.0, -9.81], (count, 1))
    earth = np.array([19.0, 0.0, 46.0])
    field = np.column_stack([np.cos(heading) * earth[0], -np.sin(heading) * earth[0], np.full(count, earth[2])])
    filter_ = fusion.Fusion(period)
    state = types.SimpleNamespace(filter=filter_, drift=None)
    take_drift(state, None)
    assert getattr(state, "loop", None) is None
    for start in range(0, 250, 25):
        filter_.update(gyr[start : start + 25], acc[start : start + 25], field[start : start + 25])
    filter_.restart_magnetometer()
    take_drift(state, lambda raw_vqf, gyr_vqf: raw_vqf)
    assert state.loop is not None and filter_.heading_bias is None
    for start in range(250, count, 25):
        filter_.update(gyr[start : start + 25], acc[start : start + 25], field[start : start + 25])
        cd.note_loop(state, False)
    learnt = -math.degrees(float(filter_._filter.getBiasEstimate()[0][2]))  # vqf's z is up: FRD z's bias negated
    assert 0.3 < learnt < 0.5  # 0.39
    aided = fusion.Fusion(period)
    aided.update(gyr[:10], acc[:10], field[:10], t[:10], np.tile([1.0, 0.0, 0.0], (10, 1)))
    assert aided.aided
    aided_state = types.SimpleNamespace(filter=aided, drift=None)
    take_drift(aided_state, lambda raw_vqf, gyr_vqf: raw_vqf)
    assert getattr(aided_state, "loop", None) is None


def test_a_shift_of_delta_is_not_read_as_a_drift() -> None:
    """``causal_drift.delta_moved`` (a refresh moved vqf's delta at once, ``refresh_shift``) moves the bias loop's last
    delta with it, so that its next step sees no change; nothing without a loop."""
    state = types.SimpleNamespace(filter=fusion.Fusion(0.02), drift=None)
    cd.delta_moved(state, 0.1)
    take_drift(state, lambda raw_vqf, gyr_vqf: raw_vqf)
    heading = state.loop[2]
    heading.delta = 3.1
    cd.delta_moved(state, 0.1)
    assert heading.delta == pytest.approx(3.2 - 2.0 * math.pi)


def test_a_records_offset_error_at_a_corner_is_not_taken_for_a_bias() -> None:
    """A level walker, no bias, 16 s of history with a corner of 90 deg in the middle, the record's offset 1 uT off
    along the body's x axis: the field's angle steps by about 3 deg at the corner (1 uT across 19 uT horizontal),
    which a line through 8 s either side reads as a drift of 0.2-0.3 deg/s. With the offset error fitted beside the
    bias (``drift_bias.offset_columns``) the step is the offset's, and the bias stays near zero."""
    rng = np.random.default_rng(5)
    t = np.arange(0.5, 16.5, 0.5)
    heading = np.where(t < 8.0, 0.0, math.pi / 2)
    quat = np.column_stack([np.cos(heading / 2), np.zeros(len(t)), np.zeros(len(t)), np.sin(heading / 2)])
    earth = np.array([0.0, 19.0, -46.0])  # ENU
    cos, sin = np.cos(heading), np.sin(heading)  # the Earth's field turned into the body, 1 uT left on its x
    field = np.column_stack([cos * earth[0] + sin * earth[1], cos * earth[1] - sin * earth[0], 0.0 * t + earth[2]])
    field[:, 0] += 1.0
    angle = vb.field_angle_rad(quat, field) + np.radians(0.5) * rng.standard_normal(len(t))
    up = vb.up_in_body(quat)
    plain = vb.fit_drift(angle, up, 0.5, min_span_s=8.0, prior_dps=cd.PRIOR_DPS)
    columns = vb.offset_columns(quat, field)
    fitted = vb.fit_drift(
        angle, up, 0.5, min_span_s=8.0, prior_dps=cd.PRIOR_DPS, nuisance=columns, nuisance_sigma=cd.OFFSET_SIGMA_UT
    )
    assert plain is not None and fitted is not None
    assert abs(math.degrees(plain.along_up_rads)) > 0.15  # 0.25 deg/s when measured
    assert abs(math.degrees(fitted.along_up_rads)) < 0.06  # 0.04
    assert fitted.residual_rad < plain.residual_rad  # the step explained
