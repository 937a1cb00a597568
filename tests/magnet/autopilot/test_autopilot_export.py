"""``magnet export``: the parameters, applied by each autopilot's own formula (written here from its source, not from
magnet's code), give magnet's calibrated field; what an autopilot cannot represent is refused with the reason."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from magnet.autopilot.conventions import ardupilot_raw_field, ardupilot_soft_iron
from magnet.autopilot.params import ardupilot_parameters, px4_parameters
from magnet.calibration import FitInput, fit
from magnet.frames import rotation_matrix
from magnet.model import Calibration
from services.cli import main

HALF_SQRT_2 = math.sqrt(0.5)


@pytest.fixture(scope="module")
def fitted() -> tuple[Calibration, np.ndarray]:
    """An ellipsoid fit of simulated samples with hard and soft iron, and those raw samples (uT)."""
    from logfixtures import simulated_run

    run = simulated_run(count=800)
    return fit(FitInput(run.mag_ut, acc=run.acc_ms2, field_ut=50.0), "ellipsoid"), run.mag_ut


def _write(calibration: Calibration, path: Path) -> Path:
    import json

    path.write_text(json.dumps(calibration.to_dict()))
    return path


# ------------------------------------------------------- each autopilot's correction, as its source states it


def ardupilot_corrected(raw_mg: np.ndarray, params: dict[str, float], suffix: str = "") -> np.ndarray:
    """AP_Compass_Backend: add COMPASS_OFS, multiply by COMPASS_SCALE when it is within 0.85..1.4, then by the
    symmetric matrix [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]; milligauss."""
    ofs = np.array([params[f"COMPASS_OFS{suffix}_{a}"] for a in "XYZ"])
    d = [params[f"COMPASS_DIA{suffix}_{a}"] for a in "XYZ"]
    o = [params[f"COMPASS_ODI{suffix}_{a}"] for a in "XYZ"]
    scale = params.get(f"COMPASS_SCALE{suffix}", 0.0)
    field = raw_mg + ofs
    if 0.85 <= scale <= 1.4:
        field = field * scale
    return field @ np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]]).T


def px4_corrected(raw_gauss: np.ndarray, params: dict[str, float], slot: int, rotation: np.ndarray) -> np.ndarray:
    """PX4 calibration::Magnetometer::Correct: rotation * (scale * (data - offset)), the scale matrix with
    CAL_MAGn_{X,Y,Z}SCALE on its diagonal and X/Y/ZODIAG at (0,1), (0,2), (1,2) mirrored; gauss."""
    p = f"CAL_MAG{slot}_"
    off = np.array([params[f"{p}{a}OFF"] for a in "XYZ"])
    d = [params[f"{p}{a}SCALE"] for a in "XYZ"]
    o = [params[f"{p}{a}ODIAG"] for a in "XYZ"]
    scale = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    return (raw_gauss - off) @ scale.T @ rotation.T


def ardupilot_file(path: Path) -> dict[str, float]:
    """The file as MAVProxy loads it: pymavlink's own parameter-file reader."""
    from pymavlink.mavparm import MAVParmDict

    params = MAVParmDict()
    assert params.load(str(path))
    return dict(params)


def px4_file(path: Path) -> dict[str, float]:
    """QGroundControl's layout: '#' comments, then vehicle, component, name, value, type separated by tabs."""
    out = {}
    for line in path.read_text().splitlines():
        if line.startswith("#"):
            continue
        vehicle, component, name, value, kind = line.split("\t")
        assert (vehicle, component) == ("1", "1") and kind in ("6", "9")
        out[name] = float(value)
    return out


def _relative_error(got: np.ndarray, want: np.ndarray) -> float:
    return float((np.linalg.norm(got - want, axis=1) / np.linalg.norm(want, axis=1)).max())


# ------------------------------------------------------------------------------------------------ round trips


def test_ardupilot_round_trip(fitted, tmp_path: Path, capsys) -> None:
    calibration, raw_ut = fitted
    out = tmp_path / "compass.param"
    args = ["export", "--calibration", str(_write(calibration, tmp_path / "cal.json")), "--format", "ardupilot"]
    assert main([*args, "--instance", "1", "--out", str(out)]) == 0
    params = ardupilot_file(out)
    assert set(params) == {f"COMPASS_{k}2_{a}" for k in ("OFS", "DIA", "ODI") for a in "XYZ"} | {"COMPASS_SCALE2"}
    got_mg = ardupilot_corrected(raw_ut * 10, params, "2")
    assert _relative_error(got_mg / 10, calibration.apply(raw_ut)) < 1e-3


def test_px4_round_trip(fitted, tmp_path: Path) -> None:
    calibration, raw_ut = fitted
    out = tmp_path / "compass.params"
    path = _write(calibration, tmp_path / "cal.json")
    assert main(["export", "--calibration", str(path), "--format", "px4", "--instance", "2", "--out", str(out)]) == 0
    params = px4_file(out)
    assert len(params) == 9 and "CAL_MAG2_XODIAG" in params
    got_gauss = px4_corrected(raw_ut / 100, params, 2, np.eye(3))
    assert _relative_error(got_gauss * 100, calibration.apply(raw_ut)) < 1e-3


def test_px4_round_trip_with_a_board_rotation_in_force(fitted) -> None:
    """Samples taken in the body frame of a board mounted yaw 180: PX4 corrects in the sensor's axes, then rotates."""
    calibration, raw_ut = fitted
    rotation = rotation_matrix(4)
    sensor_ut = raw_ut @ rotation  # what the sensor read: rotation.T @ u
    export = px4_parameters(calibration, 0, rotation_in_force=4)
    params = {p.name: p.value for p in export.parameters}
    assert "CAL_MAG0_ROT" not in params  # unchanged
    got = px4_corrected(sensor_ut / 100, params, 0, rotation) * 100
    assert _relative_error(got, calibration.apply(raw_ut)) < 1e-3


def test_a_named_rotation_becomes_the_orientation_parameter(fitted) -> None:
    calibration, raw_ut = fitted
    yaw90 = rotation_matrix(2)
    # ArduPilot: B = W (R s + o) -> a record whose matrix is W R; PX4: B = R S (s - o) -> a record R S
    mounted = calibration.replace(matrix=calibration.matrix @ yaw90)
    export = ardupilot_parameters(mounted)
    params = {p.name: p.value for p in export.parameters}
    assert params["COMPASS_ORIENT"] == 2 and any("COMPASS_ORIENT changes to 2" in n for n in export.notes)
    rotated = raw_ut @ yaw90.T  # ArduPilot's rotation of the sensor reading, checked below from its source
    assert _relative_error(ardupilot_corrected(rotated * 10, params) / 10, mounted.apply(raw_ut)) < 1e-3
    px4 = px4_parameters(calibration.replace(matrix=yaw90 @ calibration.matrix))
    p = {q.name: q.value for q in px4.parameters}
    assert p["CAL_MAG0_ROT"] == 2
    got = px4_corrected(raw_ut / 100, p, 0, yaw90) * 100
    assert _relative_error(got, calibration.replace(matrix=yaw90 @ calibration.matrix).apply(raw_ut)) < 1e-3


def test_named_rotations_match_ardupilots_component_formulas() -> None:
    """Vector3::rotate in AP_Math for a few orientations, as the source spells them out component by component."""
    x, y, z = 1.0, 2.0, 3.0
    expected = {
        2: (-y, x, z),  # yaw 90
        9: (HALF_SQRT_2 * (x + y), HALF_SQRT_2 * (x - y), -z),  # roll 180, yaw 45
        24: (z, y, -x),  # pitch 90
        28: (y, -z, -x),  # roll 90, pitch 90
        20: (x, z, -y),  # roll 270
    }
    for number, want in expected.items():
        assert rotation_matrix(number) @ np.array([x, y, z]) == pytest.approx(want), number


# ---------------------------------------------------------------------------------------------------- refusals


def test_what_an_autopilot_cannot_represent_is_refused(fitted, tmp_path: Path, capsys) -> None:
    calibration, _ = fitted
    c, s = math.cos(math.radians(3)), math.sin(math.radians(3))
    twisted = calibration.replace(matrix=np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ calibration.matrix)
    for export in (ardupilot_parameters, px4_parameters):
        with pytest.raises(ValueError, match=r"rotates the field by 3\.\d\d deg, .*nearest named orientation, 0"):
            export(twisted)
    with pytest.raises(ValueError, match=r"diagonals in \(0.2, 5\)"):
        ardupilot_parameters(calibration.replace(matrix=np.diag([6.0, 6.0, 6.0])))
    with pytest.raises(ValueError, match="COMPASS_OFFS_MAX"):
        ardupilot_parameters(calibration.replace(offset=np.array([200.0, 0.0, 0.0])))
    with pytest.raises(ValueError, match="known units"):
        px4_parameters(calibration.replace(unit="counts", output_unit="counts"))
    out = tmp_path / "out.param"
    path = _write(twisted, tmp_path / "twisted.json")
    assert main(["export", "--calibration", str(path), "--format", "ardupilot", "--out", str(out)]) == 2
    assert main(["export", "--calibration", str(path), "--format", "px4", "--instance", "4"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "rotates the field" in err[0] and "instances 0..3" in err[1]
    assert not out.exists()


def test_ardupilot_log_inversion_undoes_the_correction() -> None:
    rng = np.random.default_rng(1)
    raw = rng.normal(0, 300, (20, 3))
    soft = ardupilot_soft_iron([1.05, 0.97, 1.1], [0.02, -0.01, 0.03])
    ofs, mot = np.array([-50.0, 80.0, 120.0]), np.array([3.0, -2.0, 5.0])
    logged = 1.2 * (raw + ofs) @ soft.T + mot  # ArduPilot's order: offsets, scale, matrix, then motor offsets
    assert ardupilot_raw_field(logged, ofs, mot, soft, 1.2) == pytest.approx(raw)
    assert ardupilot_raw_field(logged / 1.2, ofs, mot / 1.2, soft, 2.0) == pytest.approx(raw)  # 2.0: not applied


# ------------------------------------------------------------------------------------- motor interference


@pytest.mark.parametrize("kind", ["current", "throttle"])
def test_motor_model_round_trip_per_autopilot(fitted, kind: str) -> None:
    """With a motor model, each autopilot's own formula (ArduPilot: COMPASS_MOT x added after its matrix, in mGauss;
    PX4: CAL_MAGn_xCOMP x power added to the reading before offset and matrix, power = throttle or current in kA)
    gives magnet's compensated field: calibration applied, then the motors' field m x taken away."""
    import dataclasses

    from magnet.motor import MotorModel

    calibration, raw_ut = fitted
    motor = MotorModel(kind, np.array([4.0, -2.5, 7.0]) / (20.0 if kind == "current" else 1.0))
    calibration = dataclasses.replace(calibration, motor=motor)
    x = np.linspace(0.0, 20.0 if kind == "current" else 1.0, len(raw_ut))
    measured = raw_ut + np.linalg.solve(calibration.matrix, (x[:, None] * motor.coefficients).T).T
    want = calibration.apply(measured) - x[:, None] * motor.coefficients
    assert _relative_error(calibration.apply(raw_ut), want) < 1e-9  # the motors' field is exactly what was added

    ap = {p.name: p.value for p in ardupilot_parameters(calibration, 0).parameters}
    assert ap["COMPASS_MOTCT"] == (2 if kind == "current" else 1)
    mot = np.array([ap[f"COMPASS_MOT_{a}"] for a in "XYZ"])
    got_ap = (ardupilot_corrected(measured * 10, ap) + x[:, None] * mot) / 10
    assert _relative_error(got_ap, want) < 1e-3

    px4 = {p.name: p.value for p in px4_parameters(calibration, 1).parameters}
    assert px4["CAL_MAG_COMP_TYP"] == (2 if kind == "current" else 1)
    power = x / 1000.0 if kind == "current" else x
    comp = np.array([px4[f"CAL_MAG1_{a}COMP"] for a in "XYZ"])
    got_px4 = px4_corrected(measured / 100 + power[:, None] * comp, px4, 1, np.eye(3)) * 100
    assert _relative_error(got_px4, want) < 1e-3


def test_a_small_rotation_the_autopilot_cannot_apply_is_dropped_with_its_angle(fitted) -> None:
    calibration, _ = fitted
    c, s = math.cos(math.radians(0.34)), math.sin(math.radians(0.34))  # a gyro-ellipsoid's alignment, say
    twisted = calibration.replace(matrix=np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ calibration.matrix)
    for export, name in ((ardupilot_parameters, "COMPASS_ORIENT"), (px4_parameters, "CAL_MAG0_ROT")):
        plain, dropped = export(calibration), export(twisted)
        assert any("rotates the field by 0.34 deg" in note and "dropped" in note for note in dropped.notes)
        assert not any("rotates" in note for note in plain.notes)
        values = {p.name: p.value for p in dropped.parameters}
        assert all(values[p.name] == pytest.approx(p.value, abs=0.02) for p in plain.parameters), name
        assert not any(p.name.startswith(name) for p in dropped.parameters)  # the orientation stays as it was


@pytest.mark.parametrize("fmt, slot", [("px4", "CAL_MAG2_XOFF"), ("ardupilot", "COMPASS_OFS3_X")])
def test_the_instance_defaults_to_the_devices_own(fitted, tmp_path: Path, capsys, fmt, slot) -> None:
    calibration, _ = fitted
    path = _write(calibration, tmp_path / "mav1-mag2.json")
    import json

    record = json.loads(path.read_text())
    path.write_text(json.dumps({**record, "device": "mav1-mag2"}))  # as magnet get calibration prints it
    assert main(["export", "--calibration", str(path), "--format", fmt]) == 0
    assert slot in capsys.readouterr().out
    assert main(["export", "--calibration", str(path), "--format", fmt, "--instance", "0"]) == 0
    assert slot not in capsys.readouterr().out  # an instance given wins
