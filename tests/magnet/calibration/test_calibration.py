"""Calibration methods on synthetic data with known truth: recovery, invariances, refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magnet.calibration import FitError, FitInput, Method, fit, fit_shape
from magnet.frames import axis_angle_matrix, random_rotations, rotation_angle_deg
from magnet.quality import GateThresholds, gate

FIELD_UT = 50.0
DIP_DEG = 65.0


# ------------------------------------------------------------------------------------------------- helpers


def unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def symmetric_soft_iron(rng: np.random.Generator, amplitude: float) -> np.ndarray:
    """A symmetric positive-definite matrix I + E with |E_ij| <= amplitude."""
    e = rng.uniform(-amplitude, amplitude, size=(3, 3))
    return np.eye(3) + (e + e.T) / 2


def distort(field: np.ndarray, correction: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Raw readings u = correction^-1 B + offset for true fields B (N, 3)."""
    return field @ np.linalg.inv(correction).T + offset


def polar_rotation(matrix: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(matrix)
    return u @ vt


def tumble(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(field (n,3) uT, specific force (n,3) m/s^2) in the body frame for random attitudes."""
    dip = math.radians(DIP_DEG)
    field_ned = FIELD_UT * np.array([math.cos(dip), 0.0, math.sin(dip)])
    world_to_body = random_rotations(n, rng)
    field = world_to_body @ field_ned
    acc = world_to_body @ np.array([0.0, 0.0, -9.81])
    return field, acc


# ------------------------------------------------------------------------------------------------- recovery


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), hard_factor=st.floats(0.0, 3.0), soft=st.floats(0.0, 0.2))
def test_ellipsoid_recovers_hard_and_soft_iron(seed, hard_factor, soft):
    rng = np.random.default_rng(seed)
    correction = symmetric_soft_iron(rng, soft)
    offset = unit_vectors(rng, 1)[0] * hard_factor * FIELD_UT
    field = unit_vectors(rng, 2000) * FIELD_UT
    raw = distort(field, correction, offset) + rng.normal(scale=0.3, size=field.shape)
    cal = fit(FitInput(raw, field_ut=FIELD_UT), Method.ELLIPSOID)
    assert np.allclose(cal.offset, offset, atol=0.15)
    assert np.allclose(cal.matrix, correction, atol=5e-3)
    # +-20 % soft iron can scale the raw radius beyond the default +-15 % radius check, which is right to flag it
    accepted, reason = gate(cal.quality, GateThresholds(radius_tolerance_pct=35.0))
    assert accepted, reason
    assert cal.quality["residual_rms_ut"] < 0.4


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), shift=st.tuples(*[st.floats(-500, 500)] * 3))
def test_translating_the_data_shifts_only_the_offset(seed, shift):
    rng = np.random.default_rng(seed)
    raw = distort(unit_vectors(rng, 500) * FIELD_UT, symmetric_soft_iron(rng, 0.2), rng.normal(size=3) * 40)
    raw += rng.normal(scale=0.5, size=raw.shape)
    base, _ = fit_shape(FitInput(raw), "ellipsoid")
    moved, _ = fit_shape(FitInput(raw + np.array(shift)), "ellipsoid")
    assert np.allclose(moved.offset - base.offset, shift, atol=1e-6)
    assert np.allclose(moved.matrix, base.matrix, atol=1e-8)


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), method=st.sampled_from(["minmax", "sphere", "ellipsoid"]))
def test_apply_then_invert_round_trips(seed, method):
    rng = np.random.default_rng(seed)
    raw = distort(unit_vectors(rng, 300) * FIELD_UT, symmetric_soft_iron(rng, 0.2), rng.normal(size=3) * 60)
    cal, _ = fit_shape(FitInput(raw), method)
    back = np.linalg.solve(cal.matrix, cal.apply(raw).T).T + cal.offset
    assert np.allclose(back, raw, atol=1e-8)


@settings(max_examples=10, deadline=None)
@given(gains=st.tuples(*[st.floats(0.6, 1.6)] * 3), offset=st.tuples(*[st.floats(-150, 150)] * 3))
def test_minmax_recovers_axis_aligned_scale(gains, offset):
    rng = np.random.default_rng(1)
    directions = np.vstack([np.eye(3), -np.eye(3), unit_vectors(rng, 200)])
    raw = directions * FIELD_UT * np.array(gains) + np.array(offset)
    cal = fit(FitInput(raw, field_ut=FIELD_UT), "minmax")
    assert np.allclose(cal.offset, offset, atol=1e-9)
    assert np.allclose(np.diag(cal.matrix), 1.0 / np.array(gains), rtol=1e-9)
    assert np.allclose(np.linalg.norm(cal.apply(directions[:6] * FIELD_UT * gains + offset), axis=1), FIELD_UT)


def test_sphere_recovers_hard_iron_and_radius():
    rng = np.random.default_rng(3)
    raw = unit_vectors(rng, 1000) * 48.0 + np.array([30.0, -70.0, 12.0]) + rng.normal(scale=0.3, size=(1000, 3))
    cal = fit(FitInput(raw), "sphere")
    assert np.allclose(cal.offset, [30.0, -70.0, 12.0], atol=0.1)
    assert cal.field_strength == pytest.approx(48.0, abs=0.05)
    assert cal.output_unit == "ut"


def test_robust_extremes_resist_a_spike():
    rng = np.random.default_rng(4)
    raw = unit_vectors(rng, 3000) * FIELD_UT
    raw[1500] = [900.0, 0.0, 0.0]  # one wild sample
    plain = fit(FitInput(raw), "minmax")
    robust = fit(FitInput(raw, robust_extremes=True), "minmax")
    assert plain.offset[0] > 400  # the spike drags the plain extremes
    # seed 003's pull moves an extreme a fifth of the way to the spike, so a lone spike does a fifth of the harm
    assert abs(robust.offset[0]) < 0.25 * abs(plain.offset[0])


@pytest.mark.parametrize("spike_ut", [30.0, 600.0])  # moderate (inside 3 radii) and gross spikes
def test_ellipsoid_leaves_spikes_out(spike_ut):
    rng = np.random.default_rng(11)
    correction = symmetric_soft_iron(rng, 0.2)
    offset = np.array([80.0, -40.0, 100.0])
    raw = distort(unit_vectors(rng, 3000) * FIELD_UT, correction, offset) + rng.normal(scale=0.3, size=(3000, 3))
    spiky = raw.copy()
    hit = rng.choice(len(raw), 45, replace=False)  # 1.5 % of the samples
    spiky[hit] += unit_vectors(rng, len(hit)) * spike_ut
    cal = fit(FitInput(spiky, field_ut=FIELD_UT), "ellipsoid")
    assert np.allclose(cal.offset, offset, atol=0.15)
    assert np.allclose(cal.matrix, correction, atol=5e-3)
    assert "outlier sample(s) left out" in cal.reason
    dropped = int(cal.reason.split(" outlier")[0].split()[-1])
    assert 35 <= dropped <= 50


def test_minmax2d_follows_the_seed_formula_and_leaves_z_alone():
    angle = np.radians(np.arange(0, 360, 2))
    raw = np.column_stack([20 * np.cos(angle) + 5, 30 * np.sin(angle) - 8, np.full(angle.shape, -40.0)])
    cal = fit(FitInput(raw, unit="ut"), "minmax2d")
    assert np.allclose(cal.offset, [5, -8, 0])
    assert np.allclose(cal.matrix, np.diag([1.5, 1.0, 1.0]))  # Xsf = 60/40, Ysf = max(1, 40/60)
    assert cal.quality["geometry"] == "circle"
    assert cal.quality["residual_rms_pct"] < 1e-6
    assert cal.accepted, cal.reason


def test_units_scale_the_output():
    rng = np.random.default_rng(5)
    raw_gauss = (unit_vectors(rng, 500) * FIELD_UT + [10, 20, 30]) / 100.0
    cal = fit(FitInput(raw_gauss, unit="gauss"), "ellipsoid")
    assert cal.output_unit == "ut" and cal.unit == "gauss"
    assert cal.field_strength == pytest.approx(FIELD_UT, rel=1e-6)
    counts = fit(FitInput(raw_gauss * 1090, unit="counts"), "ellipsoid")
    assert counts.output_unit == "counts"
    assert counts.field_strength == pytest.approx(FIELD_UT / 100 * 1090, rel=1e-6)
    scaled = fit(FitInput(raw_gauss * 1090, unit="counts", field_ut=48.0), "ellipsoid")
    assert scaled.output_unit == "ut"
    assert np.linalg.norm(scaled.apply(raw_gauss * 1090), axis=1).mean() == pytest.approx(48.0, rel=1e-4)


# ------------------------------------------------------------------------------------------------- alignment


def test_ellipsoid_align_recovers_a_5_degree_misalignment():
    rng = np.random.default_rng(7)
    field, acc = tumble(rng, 4000)
    misalignment = axis_angle_matrix([1.0, -2.0, 0.5], 5.0)
    soft = symmetric_soft_iron(rng, 0.15)
    raw = distort(field, misalignment @ soft, [40.0, -90.0, 25.0]) + rng.normal(scale=0.3, size=field.shape)
    acc_noisy = acc + rng.normal(scale=0.02, size=acc.shape)
    plain = fit(FitInput(raw, acc=acc_noisy, field_ut=FIELD_UT), "ellipsoid")
    aligned = fit(FitInput(raw, acc=acc_noisy, field_ut=FIELD_UT), "ellipsoid+align")
    assert rotation_angle_deg(polar_rotation(plain.matrix).T @ misalignment) == pytest.approx(5.0, abs=0.1)
    error_deg = rotation_angle_deg(polar_rotation(aligned.matrix).T @ misalignment)
    assert error_deg < 0.2
    # what is left of the dip spread is the noise (0.3 uT of 50 uT is ~0.35 deg); 5 deg of misalignment adds degrees
    assert aligned.quality["dip_spread_deg"] < 0.5 < 2.0 < plain.quality["dip_spread_deg"]
    assert "misalignment" in aligned.reason


def test_ellipsoid_align_says_not_observable_for_level_gravity():
    rng = np.random.default_rng(8)
    field, _ = tumble(rng, 2000)
    raw = distort(field, axis_angle_matrix([0, 0, 1], 5.0), [10.0, 0.0, 0.0])
    level = np.tile([0.0, 0.0, -9.81], (len(raw), 1))
    cal = fit(FitInput(raw, acc=level), "ellipsoid+align")
    assert "not observable" in cal.reason and "gravity directions do not span" in cal.reason
    plain, _ = fit_shape(FitInput(raw), "ellipsoid")
    assert np.allclose(cal.matrix, plain.matrix)


# ------------------------------------------------------------------------------------------------- refusals


def _sphere_samples(n: int = 200) -> np.ndarray:
    return unit_vectors(np.random.default_rng(9), n) * FIELD_UT


@pytest.mark.parametrize("method", ["minmax", "sphere", "ellipsoid"])
def test_too_few_samples(method):
    with pytest.raises(FitError, match="only 5 samples"):
        fit(FitInput(_sphere_samples(5)), method)


def test_non_finite_values():
    raw = _sphere_samples()
    raw[17, 1] = np.nan
    with pytest.raises(FitError, match=r"NaN or infinite.*row 17"):
        fit(FitInput(raw), "ellipsoid")


@pytest.mark.parametrize("shape", [(100,), (100, 2), (3, 100, 3)])
def test_wrong_shape(shape):
    with pytest.raises(FitError, match=r"\(N, 3\)"):
        fit(FitInput(np.ones(shape)), "ellipsoid")


@pytest.mark.parametrize("method", ["minmax", "sphere", "ellipsoid", "ellipsoid+align"])
def test_coplanar_level_turn_is_refused_by_3d_methods(method):
    angle = np.linspace(0, 2 * np.pi, 400)
    raw = np.column_stack([20 * np.cos(angle), 20 * np.sin(angle), np.full(angle.shape, 45.0)])
    with pytest.raises(FitError, match="coplanar"):
        fit(FitInput(raw, acc=np.tile([0, 0, -9.81], (400, 1))), method)


def test_hyperboloid_is_not_an_ellipsoid():
    rng = np.random.default_rng(10)
    z = rng.uniform(-2, 2, 1000)
    phi = rng.uniform(0, 2 * np.pi, 1000)
    r = np.sqrt(1 + z * z)
    raw = 30 * np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    with pytest.raises(FitError, match="hyperboloid"):
        fit(FitInput(raw), "ellipsoid")


def test_align_without_acc_and_bad_acc():
    with pytest.raises(FitError, match="needs accelerometer"):
        fit(FitInput(_sphere_samples()), "ellipsoid+align")
    with pytest.raises(FitError, match="shape"):
        fit(FitInput(_sphere_samples(), acc=np.ones((10, 3))), "ellipsoid+align")


def test_unknown_method_and_bad_field():
    with pytest.raises(ValueError, match="unknown calibration method 'bogus'"):
        fit(FitInput(_sphere_samples()), "bogus")
    with pytest.raises(FitError, match="positive"):
        fit(FitInput(_sphere_samples(), field_ut=-3.0), "ellipsoid")


def test_turntable_through_fit_points_to_fit_turntable():
    with pytest.raises(FitError, match="fit_turntable"):
        fit(FitInput(_sphere_samples()), "turntable")
