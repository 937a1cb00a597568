"""The heading uncertainty model (``magnet.attitude.uncertainty``): each of its four parts against the physics it
states, on samples whose answer is known by hand."""

import itertools
import math

import numpy as np
import pytest

from magnet.attitude.heading import HeadingFlag
from magnet.attitude.uncertainty import UNCALIBRATED_FRACTION, UNLEVEL_DEG, FilterFigures, HeadingUncertainty

G = 9.80665
DIP = math.radians(60.0)
B_H, B_V = 20.0, 20.0 * math.tan(DIP)  # level device facing north: field (B_h, 0, B_v) in FRD
FUSED = int(HeadingFlag.FUSED)


def _samples(n, acc=(0.0, 0.0, -G)):
    t_ns = np.arange(n, dtype=np.int64) * 10_000_000 + 10**18
    field = np.tile([B_H, 0.0, B_V], (n, 1))
    return t_ns, np.tile(acc, (n, 1)).astype(float), field


def _step(model, n, flags, residual, figures=None, quat=None, acc=(0.0, 0.0, -G), expected=np.nan, field=None):
    t_ns, acc_ms2, f = _samples(n, acc)
    f = f if field is None else field
    return model.step(
        ["d"], [0, n], t_ns, acc_ms2, f, np.full(n, flags), quat, np.full(n, expected), [residual], [figures]
    ).heading_deg


def test_a_level_still_heading_from_the_field_has_the_residual_over_the_horizontal_field():
    sigma = _step(HeadingUncertainty(), 5, 0, 0.5)
    np.testing.assert_allclose(sigma, math.degrees(0.5 / B_H))


def test_without_calibration_the_error_is_a_tenth_of_the_field_and_without_accelerometer_the_tilt_is_unknown():
    uncalibrated = _step(HeadingUncertainty(), 3, 0, None)
    norm = math.hypot(B_H, B_V)
    np.testing.assert_allclose(uncalibrated, math.degrees(UNCALIBRATED_FRACTION * norm / B_H))
    no_acc = _step(HeadingUncertainty(), 3, 0, 0.5, acc=(np.nan, np.nan, np.nan))
    # taken as level: dip seen from a field assumed level is atan(B_v / B_h), the tilt UNLEVEL_DEG
    tilt = math.radians(UNLEVEL_DEG) * math.tan(DIP)
    np.testing.assert_allclose(no_acc, math.degrees(math.hypot(0.5 / B_H, tilt)), rtol=1e-9)


def test_a_flagged_disturbance_adds_its_field_over_the_horizontal_field():
    norm = math.hypot(B_H, B_V)
    quiet = _step(HeadingUncertainty(), 3, 0, 0.5, expected=norm - 10.0)
    disturbed = _step(HeadingUncertainty(), 3, int(HeadingFlag.FIELD_DISTURBED), 0.5, expected=norm - 10.0)
    np.testing.assert_allclose(quiet, math.degrees(0.5 / B_H))
    np.testing.assert_allclose(disturbed, math.degrees(math.hypot(0.5 / B_H, 10.0 / B_H)))


def test_an_accelerometer_reading_off_g_tilts_the_heading_from_the_field():
    sigma = _step(HeadingUncertainty(), 3, 0, 0.0, acc=(0.0, 0.0, -G * 1.05))
    np.testing.assert_allclose(sigma, math.degrees(0.05 * math.tan(DIP)), rtol=1e-9)


def test_fused_the_residual_averages_over_the_magnetic_time_constant():
    quat = np.tile([1.0, 0, 0, 0], (100, 1))
    sigma = _step(HeadingUncertainty(), 100, FUSED, 0.5, FilterFigures(tau_mag_s=9.0), quat)
    np.testing.assert_allclose(sigma[1:], math.degrees(0.5 / B_H * math.sqrt(0.01 / 18.0)), rtol=0.05)


def test_fused_while_the_field_is_rejected_the_bias_uncertainty_grows_with_time():
    model, quat, n = HeadingUncertainty(), np.tile([1.0, 0, 0, 0], (100, 1)), 100
    figures = FilterFigures(bias_sigma_rads=math.radians(0.5))
    _step(model, n, FUSED, 0.0, figures, quat)  # one second trusted
    t_ns, acc, field = _samples(n)
    t_ns = t_ns + n * 10_000_000
    flags = np.full(n, FUSED | int(HeadingFlag.FIELD_DISTURBED))
    sigma, _ = model.step(["d"], [0, n], t_ns, acc, field, flags, quat, np.full(n, np.nan), [0.0], [figures])
    since = (np.arange(n) + 1) * 0.01
    np.testing.assert_allclose(sigma, 0.5 * since, rtol=1e-6)


@pytest.mark.parametrize("aided", [False, True])
def test_fused_an_unexplained_horizontal_acceleration_tilts_the_heading_unless_the_velocity_explains_it(aided):
    """A steady 1 m/s^2 towards east that nothing explains: after many time constants the tilt is a / g about north,
    and the heading's share e tan(dip) / sqrt(2); explained by the velocity, nothing."""
    model, n = HeadingUncertainty(), 100
    quat = np.tile([1.0, 0, 0, 0], (n, 1))
    explained = (lambda t: np.tile([0.0, 1.0, 0.0], (len(t), 1))) if aided else None
    figures = FilterFigures(tau_acc_s=1.0, tau_mag_s=2.0, explained=explained, known_until_s=math.inf)
    t_ns, acc, field = _samples(n, acc=(0.0, 1.0, -G))  # body y is east for a level device facing north
    for k in range(60):
        sigma, tilt = model.step(
            ["d"],
            [0, n],
            t_ns + k * n * 10_000_000,
            acc,
            field,
            np.full(n, FUSED),
            quat,
            np.full(n, np.nan),
            [0.0],
            [figures],
        )
    expected = 0.0 if aided else math.degrees(1.0 / G * math.tan(DIP) / math.sqrt(2))
    # the dip seen through a tilted accelerometer moves a little: within 2 %
    np.testing.assert_allclose(sigma[-1], expected, rtol=0.02, atol=1e-6)
    # the tilt per horizontal axis: a / g over sqrt(2), or the floor
    np.testing.assert_allclose(tilt[-1], 0.1 if aided else math.degrees(1.0 / G / math.sqrt(2)), rtol=0.02)


def test_samples_not_explained_yet_wait_for_the_velocity():
    model, n = HeadingUncertainty(), 10
    quat = np.tile([1.0, 0, 0, 0], (n, 1))
    t_ns, acc, field = _samples(n, acc=(0.0, 3.0, -G))
    waiting = FilterFigures(explained=lambda t: np.zeros((len(t), 3)), known_until_s=0.0)
    model.step(["d"], [0, n], t_ns, acc, field, np.full(n, FUSED), quat, np.full(n, np.nan), [0.0], [waiting])
    state = model.devices["d"]
    assert len(state.waiting) == 1 and state.mag == (0.0, 0.0)


def _plain_direct(field, acc, down_fused, fused, flags, expected, residual):
    """The module's per-sample part written plainly in numpy (as it was before it was compiled): the dip against the
    fused down where fused, else the accelerometer's, else level; r / |B_h|; the accelerometer's own tilt error; the
    flagged disturbance; then the degrees."""
    from magnet.attitude import uncertainty as u

    with np.errstate(invalid="ignore", divide="ignore"):
        down = -acc / np.linalg.norm(acc, axis=1)[:, None]
        down = np.where(fused[:, None], down_fused, down)
        down = np.where(np.isfinite(down).all(axis=1)[:, None], down, [0.0, 0.0, 1.0])
        norm = np.linalg.norm(field, axis=1)
        dip = np.nan_to_num(np.arcsin(np.clip(np.sum(field * down, axis=1) / norm, -1.0, 1.0)))
        dip = np.clip(dip, -math.radians(u.MAX_DIP_DEG), math.radians(u.MAX_DIP_DEG))
        horizontal, tan_dip = norm * np.cos(dip), np.abs(np.tan(dip))
        field_rad = np.where(np.isfinite(residual), residual, UNCALIBRATED_FRACTION * norm) / horizontal
        acc_norm = np.linalg.norm(acc, axis=1)
        tilt = np.where(np.isfinite(acc_norm), np.abs(acc_norm - G) / G, math.radians(UNLEVEL_DEG))
        turn = np.abs(norm - expected) / horizontal
        flagged = (flags & (int(HeadingFlag.FIELD_DISTURBED) | int(HeadingFlag.DIP_DISTURBED))) != 0
        variance = field_rad**2 + (tilt * tan_dip) ** 2 + np.where(flagged & np.isfinite(turn), turn**2, 0.0)
        sigma = np.degrees(np.sqrt(variance))
    heading = np.where(np.isfinite(sigma), np.minimum(sigma, u.MAX_SIGMA_DEG), u.MAX_SIGMA_DEG)
    tilt_deg = np.clip(np.nan_to_num(np.degrees(tilt), nan=UNLEVEL_DEG), u.MIN_TILT_DEG, 90.0)
    return np.stack([tan_dip, field_rad, tilt, variance]), heading, tilt_deg


def test_the_compiled_per_sample_part_is_the_plain_maths():
    """``_direct`` (magnet._kernels.sigma_direct) and the degrees (sigma_degrees) against ``_plain_direct`` on random
    samples with the odd ones in: no accelerometer, a zero one, a zero field, no residual, flagged, fused."""
    from magnet import _kernels
    from magnet.attitude import uncertainty as u

    rng = np.random.default_rng(32)
    n = 3000
    field, acc = rng.normal(0, 30, (n, 3)), rng.normal(0, 6, (n, 3)) + [0, 0, -G]
    acc[::11] = np.nan
    acc[5::97] = 0.0
    field[7::131] = 0.0
    rotation = np.stack([np.eye(3)] * n)
    fused = rng.random(n) < 0.5
    rotation[fused] = np.linalg.qr(rng.normal(size=(int(fused.sum()), 3, 3)))[0]
    flags = rng.choice([0, int(HeadingFlag.FIELD_DISTURBED), int(HeadingFlag.DIP_DISTURBED), FUSED], n)
    expected = np.where(rng.random(n) < 0.2, np.nan, 50.0)
    residual = np.where(rng.random(n) < 0.3, np.nan, rng.uniform(0.1, 3.0, n))
    for rot, where in ((rotation, fused), (None, np.zeros(n, bool))):
        got = u._direct(field, acc, rot, fused, flags.astype(np.int64), expected, residual)
        want, heading, tilt_deg = _plain_direct(field, acc, rotation[:, 2, :], where, flags, expected, residual)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
        assert np.array_equal(np.isnan(got), np.isnan(want))
        got_heading, got_tilt = np.empty(n), np.empty(n)
        _kernels.sigma_degrees(got[3], got[2], u.MAX_SIGMA_DEG, UNLEVEL_DEG, u.MIN_TILT_DEG, got_heading, got_tilt)
        np.testing.assert_allclose(got_heading, heading, rtol=1e-12)
        np.testing.assert_allclose(got_tilt, tilt_deg, rtol=1e-12)


def _drift_plainly(unc, devices, bounds, t_ns, trusted, batches, figures):
    """The bias drift written plainly: batch by batch, the running maximum of the trusted times (the device's last
    trusted time before the batch where a sample is not trusted)."""
    drift = np.zeros(len(t_ns))
    for b, (device, figure) in enumerate(zip(devices, figures)):
        state = unc.devices.get(device) if batches.fused[b] else None
        if state is None or figure is None:
            continue
        if not batches.untrusted[b]:
            state.trusted_ns = batches.last_ns[b]
            continue
        rows = slice(bounds[b], bounds[b + 1])
        since = np.maximum.accumulate(np.where(trusted[rows], t_ns[rows], state.trusted_ns))
        state.trusted_ns = int(since[-1])
        drift[rows] = figure.bias_sigma_rads * (t_ns[rows] - since) * 1e-9
    return drift


def test_the_drift_of_a_whole_drain_at_once_is_the_plain_batch_by_batch_maths():
    from magnet.attitude import uncertainty as unc_module

    rng = np.random.default_rng(28)
    figure = FilterFigures(tau_mag_s=10.0, tau_acc_s=3.0, bias_sigma_rads=1e-4)
    for _ in range(400):
        count = int(rng.integers(1, 10))
        sizes = rng.integers(0, 8, count)
        bounds = np.concatenate([[0], np.cumsum(sizes)]).tolist()
        t_ns = np.cumsum(rng.integers(0, 5, bounds[-1])).astype(np.int64) + 10**18
        if bounds[-1] > 2 and rng.random() < 0.4:  # times that go back within a batch
            t_ns[rng.integers(0, bounds[-1], 2)] -= rng.integers(0, 50, 2)
        trusted = rng.random(bounds[-1]) < rng.random()
        devices = [f"d{d}" for d in rng.integers(0, 3, count)]
        last = [int(t_ns[hi - 1]) if hi > lo else 0 for lo, hi in itertools.pairwise(bounds)]
        fused = [float(n) if rng.random() < 0.9 else 0.0 for n in sizes]
        untrusted = (rng.random(count) < 0.8).tolist()
        zeros = [0.0] * count
        batches = unc_module._Batches(fused, zeros, zeros, zeros, zeros, zeros, untrusted, [0] * count, last)
        figures = [figure if rng.random() < 0.9 else None for _ in range(count)]
        whole, plain = HeadingUncertainty(10), HeadingUncertainty(10)
        for device in set(devices):
            start = 10**18 - int(rng.integers(0, 20))
            whole.devices[device] = unc_module._Device(0, start)
            plain.devices[device] = unc_module._Device(0, start)
        for _ in range(2):  # the devices' last trusted times carried on to the next drain
            expected = _drift_plainly(plain, devices, bounds, t_ns, trusted, batches, figures)
            assert np.array_equal(whole._drift(devices, bounds, t_ns, trusted, batches, figures), expected)
            carried = {d: whole.devices[d].trusted_ns for d in devices}
            assert carried == {d: plain.devices[d].trusted_ns for d in devices}


def test_the_compiled_drift_refuses_batches_beyond_the_samples():
    from magnet import _kernels

    times, drift = np.arange(4, dtype=np.int64), np.zeros(4)
    args = (
        np.zeros(4, bool),
        np.array([0, 2, 6]),
        np.array([0, 0]),
        np.ones(2, bool),
        np.ones(2),
        np.zeros(1, np.int64),
    )
    with pytest.raises(ValueError, match="out of range"):
        _kernels.bias_drift(times, *args, drift)


def _batches_plainly(bounds, t_ns, fused, trusted, tan_dip, horizontal):
    """_Batches.of's figures in numpy (as it was written before it was compiled): the rows summed by reduceat."""
    edges = np.asarray(bounds, dtype=np.int64)
    counts = np.diff(edges)
    nonempty = counts > 0
    known = fused & np.isfinite(horizontal).all(axis=1)
    t_s = (t_ns - t_ns[0]) * 1e-9 if len(t_ns) else np.zeros(0)
    rows = np.empty((7, len(t_ns)))
    rows[0], rows[2], rows[6] = fused, known, fused & ~trusted
    rows[1] = np.where(fused, tan_dip, 0.0)
    rows[3] = np.where(known, t_s, 0.0)
    rows[4:6] = np.where(known, horizontal.T, 0.0)
    sums = np.zeros((len(counts), 7))
    if nonempty.any():
        sums[nonempty] = np.add.reduceat(rows, edges[:-1][nonempty], axis=1).T
    with np.errstate(invalid="ignore", divide="ignore"):
        tan_mean, means = sums[:, 1] / sums[:, 0], sums[:, 3:6] / sums[:, 2:3]
    means[:, 0] += float(t_ns[0]) * 1e-9 if len(t_ns) else 0.0
    return [sums[:, 0], tan_mean, sums[:, 2], *means.T, sums[:, 6] > 0]


def test_the_compiled_batch_figures_are_the_reduceat_sums_bit_for_bit():
    from magnet.attitude import uncertainty as unc_module

    rng = np.random.default_rng(9)
    for _ in range(300):
        sizes = rng.integers(0, 300, int(rng.integers(1, 6)))
        bounds = np.concatenate([[0], np.cumsum(sizes)])
        count = int(bounds[-1])
        t_ns = np.cumsum(rng.integers(1, 3_000_000, count)).astype(np.int64) + 1_780_000_000 * 10**9
        fused, trusted = rng.random(count) < 0.8, rng.random(count) < rng.random()
        tan_dip = rng.normal(0, 2, count) * 10 ** rng.uniform(-3, 3, count)
        horizontal = rng.normal(0, 0.3, (count, 2))
        horizontal[rng.random(count) < 0.05, int(rng.integers(0, 2))] = np.nan
        got = unc_module._Batches.of(bounds.tolist(), t_ns, fused, trusted, tan_dip, horizontal)
        want = _batches_plainly(bounds, t_ns, fused, trusted, tan_dip, horizontal)
        for g, w in zip(got[:7], want):
            np.testing.assert_array_equal(np.array(g, dtype=float), np.asarray(w, dtype=float))
