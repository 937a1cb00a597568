"""The field ladder (``magnet.calibration.field``, ``ladder``): the model the motion identifies, judged by heading.

Motions are made here from the physics (a body turning about the vertical at a fixed tilt, the WMM's field, phone-
like hard iron of 10 times the field and a few % of soft iron), so that each test knows which parameters the motion
can show."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from magnet.calibration import FitError, Method, fit, fit_auto
from magnet.calibration.field import FieldInput, fit_field
from magnet.calibration.fit_input import FitInput
from magnet.calibration.rungs import PLANAR_NOTE
from magnet.earth.geomag import earth_field
from magnet.earth.location import Location
from magnet.frames import euler_to_matrix, matrix_to_euler, rotation_angle_deg
from magnet.model import IDENTITY, Calibration

RATE_HZ = 100.0
PERIOD_S = 1.0 / RATE_HZ
PLACE, DATE = Location(50.45, 30.52, 0.0), "2026-01-01"
EARTH = earth_field(50.45, 30.52, 0.0, DATE)
B_NED = np.array(EARTH.ned_ut)
FIELD_UT = float(np.linalg.norm(B_NED))
G_NED = np.array([0.0, 0.0, 9.80665])
HARD_UT = np.array([310.0, -420.0, 180.0])  # about 10 times the field
SOFT = np.array([[1.04, 0.02, 0.0], [0.02, 0.97, 0.0], [0.0, 0.0, 1.0]])


def turning(seconds: float, turns: float, tilt_deg: float, seed: int, sway_deg: float = 2.0) -> dict[str, np.ndarray]:
    """A body turning ``turns`` full turns about the vertical over ``seconds`` (after a 10 s straight), its z axis
    ``tilt_deg`` off the vertical (a phone held for texting), with a little sway: raw mag (uT), acc (m/s^2), gyr
    (rad/s), the true heading of body x (deg) and the true body -> NED matrices."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    u = np.clip((t - 10.0) / (seconds - 10.0), 0.0, 1.0)
    yaw = rng.uniform(0, 360) + 360.0 * turns * (3 * u**2 - 2 * u**3)
    sway = sway_deg * np.sin(2 * np.pi * 0.7 * t + rng.uniform(0, 6))
    rotation = euler_to_matrix(yaw, tilt_deg + sway, sway * 0.5)
    field_body = np.einsum("nji,j->ni", rotation, B_NED)
    mag = field_body @ SOFT.T + HARD_UT + 0.3 * rng.standard_normal(field_body.shape)
    acc = np.einsum("nji,j->ni", rotation, -G_NED) + 0.02 * rng.standard_normal(field_body.shape)
    step = np.einsum("nji,njk->nik", rotation[:-1], rotation[1:])  # R_{k-1}^T R_k
    gyr = np.zeros_like(mag)
    gyr[1:] = _log(step) * RATE_HZ
    gyr += np.array([0.004, -0.003, 0.002]) + 0.002 * rng.standard_normal(gyr.shape)
    heading = matrix_to_euler(rotation)[0]
    return {"mag": mag, "acc": acc, "gyr": gyr, "heading": heading, "rotation": rotation}


def _log(rotations: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of small rotations (N, 3, 3)."""
    angle = np.radians(rotation_angle_deg(rotations))
    skew = rotations - np.transpose(rotations, (0, 2, 1))
    axis = np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], axis=1)
    scale = np.where(angle > 1e-12, angle / (2 * np.sin(np.maximum(angle, 1e-12))), 0.5)
    return axis * scale[:, None]


def heading_error_deg(calibration: Calibration, motion: dict[str, np.ndarray]) -> float:
    """RMS (deg) of the heading the calibrated field gives with the true attitude's tilt, against the truth."""
    field = calibration.apply(motion["mag"])
    earth = np.einsum("nij,nj->ni", motion["rotation"], field)  # in NED with the true attitude
    # the heading of body x: rotate back by the field's horizontal direction (magnetic north)
    error = -np.degrees(np.arctan2(earth[:, 1], earth[:, 0])) + np.degrees(np.arctan2(B_NED[1], B_NED[0]))
    error = (error + 180.0) % 360.0 - 180.0
    return float(np.sqrt(np.mean(error**2)))


def _field_input(motion: dict[str, np.ndarray], reference: Calibration | None = None) -> FieldInput:
    return FieldInput(
        motion["mag"], motion["acc"], motion["gyr"], PERIOD_S, "ut", FIELD_UT, EARTH.inclination_deg, reference
    )


@pytest.fixture(scope="module")
def level_turns():
    return turning(50.0, 2.0, 3.0, seed=1)


def test_a_level_vehicle_gets_planar_hard_and_soft_iron_and_the_record_says_so(level_turns):
    record = fit_auto(
        FitInput(
            level_turns["mag"],
            acc=level_turns["acc"],
            gyr_rads=level_turns["gyr"],
            period_s=PERIOD_S,
            place=PLACE,
            date=DATE,
            field_ut=FIELD_UT,
        )
    )
    assert record.accepted, record.reason
    assert record.method == "planar"
    assert record.quality["planar"] == PLANAR_NOTE == "planar: within 20 deg of level"
    assert "horizontal soft iron" in record.quality["estimated"]
    assert record.quality["identified_deg"]["planar"] <= 1.5
    assert heading_error_deg(record, level_turns) < 1.5  # the noise alone leaves about 0.9 deg
    # the uncalibrated field is tens of degrees off
    assert heading_error_deg(IDENTITY, level_turns) > 20.0


def test_a_phone_held_tilted_while_its_holder_turns_is_planar_about_its_own_vertical():
    texting = turning(50.0, 2.0, 40.0, seed=2)
    record = fit_field(_field_input(texting))
    # planar identified; the offset rung, also identified, is chosen when held-out heading says it is better
    assert record.quality["identified_deg"]["planar"] <= 1.5
    assert record.method in ("planar", "offset") and record.accepted, record.reason
    assert record.quality["planar"] == PLANAR_NOTE
    assert heading_error_deg(record, texting) < 3.0  # the noise alone leaves about 0.9 deg


def test_one_slow_turn_identifies_the_offset_alone_and_the_record_says_what_was_kept():
    turn = turning(30.0, 1.0, 40.0, seed=2, sway_deg=0.5)
    record = fit_field(_field_input(turn))
    assert record.method == "offset" and record.accepted, record.reason
    assert record.quality["identified_deg"]["planar"] > 1.5 >= record.quality["identified_deg"]["offset"]
    # the ladder's offset rung keeps the matrix whole; the plain sphere (its radius free), judged better on held-out
    # heading here, keeps it up to its scale: either way the matrix kept is the identity's shape
    assert record.quality["estimated"][0] == "offset" and record.quality["kept"][0].startswith("matrix")
    assert [c["model"] for c in record.quality["candidates"]] == ["offset", "offset"]
    assert record.quality["kept_from"] == "identity"
    assert np.allclose(record.matrix, record.matrix[0, 0] * np.eye(3))
    assert heading_error_deg(record, turn) < 3.0
    assert heading_error_deg(IDENTITY, turn) > 20.0


def test_a_short_arc_identifies_nothing_and_says_what_to_do():
    arc = turning(20.0, 0.05, 3.0, seed=3, sway_deg=0.5)
    with pytest.raises(FitError, match="does not identify"):
        fit_field(_field_input(arc))


def test_a_rung_asked_for_that_the_motion_does_not_identify_is_refused_saying_what_to_do():
    """``--method offset`` on a short arc goes through the ladder's identifiability rule: refused (the ladder
    raises "does not identify" here), naming the offset's direction the arc leaves unknown and the motion to make."""
    arc = turning(20.0, 0.05, 3.0, seed=3, sway_deg=0.5)
    record = fit_field(_field_input(arc), rung="offset")
    assert not record.accepted
    assert record.reason.startswith("refused by the identifiability rule (offset asked for)"), record.reason
    assert record.quality["identified_deg"]["offset"] > 1.5
    assert "the offset along body axes" in record.reason and "more headings" in record.reason


def test_a_fit_no_better_than_the_calibration_in_force_is_refused(level_turns):
    truth = Calibration(method="truth", offset=HARD_UT, matrix=np.linalg.inv(SOFT), field_strength=FIELD_UT)
    data = FitInput(
        level_turns["mag"],
        acc=level_turns["acc"],
        gyr_rads=level_turns["gyr"],
        period_s=PERIOD_S,
        field_ut=FIELD_UT,
        dip_deg=EARTH.inclination_deg,
        reference=truth,
    )
    record = fit(data, Method.PLANAR)
    assert not record.accepted
    assert "more constant than the calibration in force" in record.reason


def test_field_methods_are_named_in_records_and_refuse_bad_input():
    assert {"offset", "offset+scale", "planar"} <= {m.value for m in Method if m.field_rung}
    with pytest.raises(FitError, match="200"):
        fit_field(FieldInput(np.zeros((50, 3))))


def test_a_vehicles_fit_against_the_record_in_force_is_judged_with_its_velocity_aided_tilt():
    """A car's sustained accelerations tilt a filter fed the raw accelerometer by several degrees; with the velocity
    (and the record in force's heading) the fit's down direction is the true one to a degree, and the record says
    its judgement was aided. Without a record in force the evidence stays unaided (docs/field-calibration.md)."""
    from magnet import frames
    from magnet.calibration.field import _aided_evidence
    from magnet.quality import motion
    from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate

    errors = SensorErrors.phone(np.random.default_rng(16), 50.0)
    run = simulate(
        SimulatorConfig(
            trajectory=Trajectory.CAR, rate_hz=50.0, count=3000, errors=errors, seed=16, lat_deg=50.45, lon_deg=30.52
        )
    )
    in_force = errors.true_calibration(run.earth.total_ut)
    inp = FieldInput(
        run.mag_ut,
        run.acc_ms2,
        run.gyr_rads,
        0.02,
        field_ut=run.earth.total_ut,
        dip_deg=run.earth.inclination_deg,
        reference=in_force,
        vel_ned_ms=run.vel_ned_ms,
        declination_deg=run.earth.declination_deg,
    )
    truth = frames.down_in_body(run.quat_wxyz)

    def tilt_error_deg(ev: motion.MotionEvidence) -> float:
        cosine = np.clip(np.einsum("ij,ij->i", ev.down, truth), -1.0, 1.0)
        return float(np.degrees(np.sqrt(np.mean(np.arccos(cosine) ** 2))))

    aided = _aided_evidence(inp)
    assert aided is not None and aided.source == motion.AIDED_SOURCE
    unaided = motion.evidence(run.acc_ms2, run.gyr_rads, 0.02)
    assert tilt_error_deg(aided) < 1.5 < 3.0 < tilt_error_deg(unaided)
    record = fit_field(inp)
    assert record.quality.get("dip_source") == motion.AIDED_SOURCE
    assert _aided_evidence(dataclasses.replace(inp, reference=None)) is None
    assert _aided_evidence(dataclasses.replace(inp, vel_ned_ms=None)) is None
