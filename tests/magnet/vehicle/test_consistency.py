"""The compasses of one simulated vehicle judged against each other (magnet.vehicle): a quadcopter's flight with
three compasses, one mounted turned, one beside the power wires; a local anomaly; a calibration gone stale; the
window the compass keeps."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from magnet.simulator import SensorErrors, SimulatorConfig, simulate
from magnet.simulator.motors import Motors
from magnet.vehicle import Series, VehicleWindows, Verdict, instance_of, judge, vehicle_of
from magnet.vehicle.consistency import parameter_names

QUIET = Motors(ut_per_a=(0.0, 0.0, 0.0))
LOUD = Motors(ut_per_a=(0.3, -0.2, 0.25))  # 0.45 uT/A: 18 uT at the 40 A of full throttle


#: each flight simulated once per run (its arrays read-only, so that no test changes another's)
_FLIGHTS: dict[str, Series] = {}


def flight(errors: SensorErrors, motors: Motors = QUIET, count: int = 600) -> Series:
    """A minute of a simulated quadcopter's flight at 10 Hz (the same flight for every compass)."""
    config = SimulatorConfig(trajectory="multirotor", rate_hz=10.0, count=count, errors=errors, seed=4, motors=motors)
    if repr(config) not in _FLIGHTS:
        run = simulate(config)
        assert run.current_a is not None and run.throttle is not None
        for array in (run.t_s, run.mag_ut, run.current_a, run.throttle):
            array.setflags(write=False)
        _FLIGHTS[repr(config)] = Series(run.t_s, run.mag_ut, run.current_a, run.throttle)
    return _FLIGHTS[repr(config)]


@functools.cache
def expected_ut() -> float:
    return float(np.linalg.norm(simulate(SimulatorConfig(count=100)).true_field_ut[0]))


def test_a_compass_mounted_turned_and_one_beside_the_motors_are_named_with_their_fix() -> None:
    series = {
        "mav1-mag0": flight(SensorErrors(noise_ut=0.3)),
        "mav1-mag1": flight(SensorErrors(noise_ut=0.3, misalignment_deg=(0.0, 0.0, 90.0))),
        "mav1-mag2": flight(SensorErrors(noise_ut=0.3), LOUD),
    }
    report = judge("mav1", series, expected_ut())
    by = {c.device: c for c in report.compasses}
    assert report.reference == "mav1-mag0" and by["mav1-mag0"].verdict is Verdict.REFERENCE
    turned = by["mav1-mag1"]
    assert turned.verdict is Verdict.ROTATION and turned.causes == (Verdict.ROTATION,)
    assert turned.named_rotation == 2 and turned.parameters == {"COMPASS_ORIENT2": 2.0, "CAL_MAG1_ROT": 2.0}
    assert turned.rotation_deg == pytest.approx(90.0, abs=1.0)
    motor = by["mav1-mag2"]
    assert motor.verdict is Verdict.INTERFERENCE and motor.causes == (Verdict.INTERFERENCE,)
    # compassmot's figure: 0.45 uT/A x the most current seen, over the most throttle seen (full throttle), / 51 uT
    assert 25.0 < (motor.interference_pct or 0) < 45.0 and (motor.correlation or 0) > 0.95
    assert motor.motor_ut == pytest.approx(LOUD.ut_per_a, abs=0.02)
    assert motor.parameters["COMPASS_MOTCT"] == 2.0 and motor.parameters["COMPASS_MOT3_X"] == pytest.approx(-3.0, 0.1)
    assert "COMPASS_ORIENT2=2" in report.summary and "mav1-mag2: interference" in report.summary
    assert not report.anomaly
    assert report.to_dict()["compasses"][1]["verdict"] == "rotation"


def test_a_current_unknown_on_most_samples_still_names_the_motors_and_the_rotation() -> None:
    """The edge attaches a current at most a second old: a vehicle whose SYS_STATUS comes late or is lost (a busy
    link, a stand-in starved of the processor) sends 1.5 s of every 2.5 s without one (nor a throttle: SERVO_OUTPUT_RAW
    comes with it). The samples with a current
    are enough: the motors are still the cause, not a calibration (before, under half the samples with a current
    dropped the current altogether, and the motors' field was called a stale calibration, 13 uT RMS)."""
    series = {
        "mav1-mag0": flight(SensorErrors(noise_ut=0.3)),
        "mav1-mag1": flight(SensorErrors(noise_ut=0.3, misalignment_deg=(0.0, 0.0, 90.0))),
        "mav1-mag2": flight(SensorErrors(noise_ut=0.3), LOUD),
    }
    late = np.arange(600) % 25 < 15  # 60 % of the samples
    series = {
        d: dataclasses.replace(
            s, current_a=np.where(late, np.nan, s.current_a), throttle=np.where(late, np.nan, s.throttle)
        )
        for d, s in series.items()
    }
    by = {c.device: c for c in judge("mav1", series, expected_ut()).compasses}
    assert by["mav1-mag1"].causes == (Verdict.ROTATION,) and by["mav1-mag1"].named_rotation == 2
    motor = by["mav1-mag2"]
    assert motor.causes == (Verdict.INTERFERENCE,) and motor.motor_per == "A", motor
    assert 25.0 < (motor.interference_pct or 0) < 45.0 and motor.motor_ut == pytest.approx(LOUD.ut_per_a, abs=0.02)


def test_compasses_that_agree_in_a_field_the_wmm_does_not_expect_are_a_local_anomaly() -> None:
    series = {f"mav2-mag{n}": flight(SensorErrors(noise_ut=0.3, soft_iron=np.eye(3) * 1.3)) for n in range(2)}
    report = judge("mav2", series, expected_ut())
    assert [c.verdict for c in report.compasses] == [Verdict.REFERENCE, Verdict.AGREES]
    assert report.anomaly and "local anomaly" in report.summary and "not the vehicle's fault" in report.summary
    assert not judge("mav2", series, None).anomaly  # no place known: no anomaly verdict


def test_a_calibration_that_no_longer_fits_is_told_from_a_rotation() -> None:
    stale = SensorErrors(noise_ut=0.3, hard_iron_ut=(9.0, -6.0, 4.0), soft_iron=np.diag([1.15, 0.9, 1.0]))
    series = {"mav3-mag0": flight(SensorErrors(noise_ut=0.3)), "mav3-mag1": flight(stale)}
    [_, other] = judge("mav3", series, expected_ut()).compasses
    assert other.verdict is Verdict.CALIBRATION and other.named_rotation is None
    assert other.residual_ut > 3.0 and "calibrate it again" in other.fix


def test_too_few_samples_and_names() -> None:
    report = judge("mav4", {"mav4-mag0": flight(SensorErrors(), count=100)}, None)
    assert report.reference is None and report.compasses[0].verdict is Verdict.TOO_FEW
    assert vehicle_of("mav12-mag2") == "mav12" and instance_of("mav12-mag2") == 2 and vehicle_of("bench-3") is None
    assert parameter_names("mav1-mag0") == ("COMPASS_ORIENT", "CAL_MAG0_ROT", "")
    assert parameter_names("mav1-mag2") == ("COMPASS_ORIENT3", "CAL_MAG2_ROT", "3")


def test_the_window_keeps_ten_samples_a_second_of_the_last_ninety_seconds() -> None:
    windows = VehicleWindows(max_vehicles=2)
    t_ns = (np.arange(1000) * 20_000_000).astype(np.int64)  # 20 s at 50 Hz
    field = np.tile([20.0, 0.0, 45.0], (1000, 1))
    nan = np.full(1000, np.nan)
    devices, bounds = ["mav1-mag0", "mav1-mag1", "bench-1"], [0, 500, 1000, 1000]
    windows.observe(devices, bounds, t_ns, field, nan, nan, lambda b: None)
    series = windows.series("mav1")
    assert set(series) == {"mav1-mag0", "mav1-mag1"} and windows.known() == ["mav1"]
    assert len(series["mav1-mag0"].t_s) == 100 and np.allclose(np.diff(series["mav1-mag0"].t_s), 0.1, atol=0.03)
    late = (t_ns + 200_000_000_000)[:500]  # 200 s later: the old rows leave the window
    matrix = np.array([[0.0, -1.2, 0.0], [1.2, 0.0, 0.0], [0.0, 0.0, 1.2]])  # a fit that turned it: 1.2 x Rz(90)
    windows.observe(["mav1-mag0"], [0, 500], late, field + 5.0, nan, nan, lambda b: (np.full(3, 5.0), matrix))
    kept = windows.series("mav1")["mav1-mag0"]
    assert kept.t_s.min() >= 200.0
    assert np.allclose(kept.field_ut[-1], [24.0, 0.0, 54.0])  # offset and the matrix's size, not its rotation


def test_the_compass_core_keeps_a_vehicles_compasses_and_judges_them() -> None:
    """Raw batches of three compasses of vehicle mav1 (and a device of no vehicle) through ``CompassCore.step``: the
    report names the turned compass and the one beside the motors."""
    from compass_steps import NOW_NS, compass_core

    from magnet import wire
    from magnet.earth.expected import Earth

    runs = {
        "mav1-mag0": flight(SensorErrors(noise_ut=0.3)),
        "mav1-mag1": flight(SensorErrors(noise_ut=0.3, misalignment_deg=(0.0, 0.0, 90.0))),
        "mav1-mag2": flight(SensorErrors(noise_ut=0.3), LOUD),
        "bench-1": flight(SensorErrors(noise_ut=0.3)),
    }
    core = compass_core(Earth(total_ut=expected_ut(), inclination_deg=67.0))
    for start in range(0, 600, 50):
        batches = []
        for device, s in runs.items():
            part = slice(start, start + 50)
            t_ns = (NOW_NS + s.t_s[part] * 1e9).astype(np.int64)
            field, current = s.field_ut[part], s.current_a[part]
            batches.append(wire.RawBatch(device, start // 50, "sim", t_ns, field, None, None, None, current_a=current))
        core.step(wire.RawColumns.from_batches(batches), NOW_NS)
    assert core.vehicles.known() == ["mav1"] and core.vehicle_report("nothing") is None
    report = core.vehicle_report("mav1")
    assert report is not None and report.expected_ut == pytest.approx(expected_ut())
    verdicts = {c.device: c.verdict for c in report.compasses}
    assert verdicts["mav1-mag0"] is Verdict.REFERENCE and verdicts["mav1-mag1"] is Verdict.ROTATION
    assert verdicts["mav1-mag2"] is Verdict.INTERFERENCE and len(verdicts) == 3


def test_a_batch_names_its_vehicle_on_the_wire_and_the_compass_groups_by_it() -> None:
    """``magnet edge --vehicle NAME``: the raw message's optional ``vehicle`` (both wire versions), checked where it
    enters, carried through the columns, and the compass groups devices of any name by it."""
    from compass_steps import NOW_NS, compass_core

    from magnet import wire

    t_ns = np.arange(3, dtype=np.int64) + NOW_NS
    batch = wire.RawBatch("bench-a", 0, "sim", t_ns, np.ones((3, 3)), vehicle="rover7")
    for version in wire.VERSIONS:
        assert wire.decode_raw(wire.encode_raw(batch, version)).vehicle == "rover7"
    plain = wire.RawBatch("bench-b", 0, "sim", t_ns, np.ones((3, 3)))
    assert b"vehicle" not in wire.encode_raw(plain)  # additive: absent unless named
    columns, errors = wire.decode_raw_many([wire.encode_raw(batch), wire.encode_raw(plain)])
    assert not errors and columns.vehicles == ["rover7", ""]
    assert columns.select(np.array([False, True])).vehicles is None
    bad = wire.pack({"v": 1, "device": "d", "seq": 0, "t_ns": [1], "mag_ut": [[1.0, 2.0, 3.0]], "vehicle": 7})
    with pytest.raises(wire.WireError, match="vehicle must be a string"):
        wire.decode_raw(bad)
    core = compass_core()
    core.step(wire.RawColumns.from_batches([batch, plain]), NOW_NS)
    assert core.vehicles.known() == ["rover7"] and list(core.vehicles.series("rover7")) == ["bench-a"]
    assert vehicle_of("bench-a", "rover7") == "rover7"


def test_the_nearest_named_rotation_is_the_frames_one() -> None:
    from magnet.frames import euler_to_matrix, nearest_rotation
    from magnet.vehicle.consistency import nearest_named

    rng = np.random.default_rng(3)
    for yaw, pitch, roll in rng.uniform(-180, 180, (20, 3)):
        matrix = euler_to_matrix(yaw, pitch / 2, roll).reshape(3, 3)
        number, angle = nearest_named(matrix)
        assert (number, angle) == pytest.approx(nearest_rotation(matrix), abs=1e-6)


def test_a_vehicle_is_one_ros2_diagnostic_status() -> None:
    """A ROS 2 diagnostic status per vehicle (``/diagnostics``): WARN naming the compasses that disagree and the
    parameters to set; OK when they agree; STALE with too few samples."""
    from rosbags.typesys import Stores, get_typestore

    from magnet.ros2 import messages
    from magnet.ros2.compass import vehicle_diagnostic

    series = {
        "mav1-mag0": flight(SensorErrors(noise_ut=0.3)),
        "mav1-mag1": flight(SensorErrors(noise_ut=0.3, misalignment_deg=(0.0, 0.0, 90.0))),
    }
    status = vehicle_diagnostic(judge("mav1", series, expected_ut()))
    array = get_typestore(Stores.ROS2_JAZZY).deserialize_cdr(
        messages.diagnostic_array_cdr(5, [status]), messages.DIAGNOSTIC_ARRAY
    )
    [read] = array.status
    values = {v.key: v.value for v in read.values}
    assert read.level == 1 and read.name == "magnet: vehicle mav1" and "COMPASS_ORIENT2=2" in read.message
    assert values["COMPASS_ORIENT2"] == "2" and values["mav1-mag1"].startswith("rotation")
    agreeing = {d: flight(SensorErrors(noise_ut=0.3)) for d in ("mav1-mag0", "mav1-mag1")}
    assert vehicle_diagnostic(judge("mav1", agreeing, expected_ut())).level == 0
    assert vehicle_diagnostic(judge("mav1", {"mav1-mag0": agreeing["mav1-mag0"]}, None)).level == 3
