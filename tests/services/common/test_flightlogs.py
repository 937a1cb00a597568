"""Flight logs as recorded inputs: a real PX4 ULog (pyulog's sample), a real ArduPilot DataFlash log (pymavlink's
test log) and a MAVLink telemetry log written by pymavlink, read through ``read_input`` and the commands."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from logfixtures import (
    ARDUPILOT_LOG,
    DATAFLASH_MAG_LAYOUTS,
    PX4_LOG,
    simulated_run,
    write_dataflash,
    write_tlog,
)

from services.cli import main
from services.common.inputs import InputOptions, read_input, reference_yaw
from services.edge.sources import read_recording

COMPARE = re.compile(r"compare: ([0-9.]+) deg RMS")


@pytest.fixture(scope="module")
def tlog(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, object]:
    run = simulated_run(count=350, rate_hz=25.0)
    path = tmp_path_factory.mktemp("tlog") / "flight.tlog"
    write_tlog(path, run)
    return path, run


# ------------------------------------------------------------------------------------------------------------- PX4


def test_px4_ulog_gives_the_magnetometer_with_imu_in_the_body_frame() -> None:
    table = read_input(PX4_LOG)
    assert "sensor_combined.magnetometer_ga" in table.note and "already calibrated" in table.note
    assert len(table.mag) > 6000  # about 100 Hz over 69 s, one row per new magnetometer sample
    field = np.linalg.norm(table.mag, axis=1)
    assert 40 < np.median(field) < 60  # uT, the Earth's field after PX4's calibration
    gravity = np.linalg.norm(table.acc, axis=1)
    assert np.median(gravity) == pytest.approx(9.81, abs=0.3)
    assert np.median(table.acc[:, 2]) < -8  # FRD: a level vehicle's accelerometer reads -g on z
    t = table.numeric("t_s")
    assert np.all(np.diff(t) > 0) and t[-1] - t[0] == pytest.approx(68.9, abs=0.5)
    assert {"gx", "gy", "gz", "throttle"} <= set(table.columns)
    assert 0 <= table.numeric("throttle").min() <= table.numeric("throttle").max() <= 1


def test_heading_compare_agrees_with_px4s_own_yaw(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["heading", str(PX4_LOG), "--compare"]) == 0
    err = capsys.readouterr().err
    rms = float(COMPARE.search(err).group(1))  # type: ignore[union-attr]
    assert rms < 0.7  # the target 1.0; 0.85 while its paired stamps (0.75 ms apart) set the period; vqf 0.27
    assert "vehicle_attitude" in err and "ATT_MAG_DECL" in err and "declination: magnet none" in err
    assert "magnet heading: PX4 ULog: sensor_combined" in err  # which stream was used


def test_px4_unknown_instance_and_missing_attitude_are_refused() -> None:
    with pytest.raises(ValueError, match=r"no magnetometer instance 2 .*instances: \[0\]"):
        read_input(PX4_LOG, InputOptions(mag=2))
    with pytest.raises(ValueError, match="needs a flight log"):
        reference_yaw("samples.csv")


def test_replay_reads_a_flight_log() -> None:
    recording = read_recording(PX4_LOG)
    assert len(recording) > 6000 and recording.gyr_rads is not None and recording.acc_ms2 is not None


# ------------------------------------------------------------------------------------------------------- ArduPilot


def _ardupilot_correction(raw_mg: np.ndarray, params: dict[str, float], ofs: np.ndarray) -> np.ndarray:
    """ArduPilot's correction as AP_Compass_Backend::correct_field applies it (written from its source): add the
    offsets, then the soft-iron matrix [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]]."""
    d = [params[f"COMPASS_DIA_{a}"] for a in "XYZ"]
    o = [params[f"COMPASS_ODI_{a}"] for a in "XYZ"]
    matrix = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    return (raw_mg + ofs) @ matrix.T


def test_ardupilot_log_mag_imu_and_parm_are_found_and_the_correction_removed() -> None:
    from pymavlink import mavutil

    table = read_input(ARDUPILOT_LOG)
    assert "MAG instance 0" in table.note and "COMPASS_DIA_*=[1.0177" in table.note
    assert "IMU 0" in table.note and "only 8 magnetometer samples" in table.note
    assert len(table.mag) == 8 and table.acc is not None
    assert np.median(table.acc[:, 2]) == pytest.approx(-9.8, abs=0.3)
    assert {"current_a", "throttle"} <= set(table.columns)
    log = mavutil.mavlink_connection(str(ARDUPILOT_LOG))
    params, mags = {}, []
    try:
        while (record := log.recv_match(type=["PARM", "MAG"])) is not None:
            if record.get_type() == "PARM":
                params.setdefault(record.Name, record.Value)
            else:
                mags.append(record)
    finally:
        log.close()
    logged = np.array([[m.MagX, m.MagY, m.MagZ] for m in mags], dtype=float)
    offsets = np.array([[m.OfsX, m.OfsY, m.OfsZ] for m in mags], dtype=float)
    assert np.abs(_ardupilot_correction(table.mag * 10, params, offsets) - logged).max() < 1e-6


def test_ardupilot_instances_by_message_name_and_a_log_too_short_to_fit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    second = read_input(ARDUPILOT_LOG, InputOptions(mag=1))
    assert "MAG instance 1" in second.note and not np.allclose(second.mag, read_input(ARDUPILOT_LOG).mag)
    with pytest.raises(ValueError, match=r"no MAG records of instance 3 \(instances: \[0, 1, 2\]\)"):
        read_input(ARDUPILOT_LOG, InputOptions(mag=3))
    out = tmp_path / "cal.json"
    assert main(["fit", str(ARDUPILOT_LOG), "--method", "ellipsoid", "--out", str(out)]) == 2
    assert "only 8 samples" in capsys.readouterr().err and not out.exists()


def test_ardupilot_compare_names_compass_dec(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["heading", str(ARDUPILOT_LOG), "--compare"]) == 0
    err = capsys.readouterr().err
    assert "ATT yaw over 8 samples" in err and "COMPASS_DEC=11.81 deg" in err


@pytest.mark.parametrize("layout", ["2013", "2014", "2016", "2020"])
def test_every_mag_layout_ardupilot_logged_reads_and_fits(layout: str, tmp_path: Path, capsys) -> None:
    """Old DataFlash logs (issue 27): MAG without motor offsets (2013), MOfsX.. with TimeMS (2014), MOfsX.. with
    TimeUS (2016), MOX.. with the instance field (2020): each reads back the reading (offsets removed) and fits."""
    run = simulated_run(count=400, rate_hz=25.0)
    path = tmp_path / f"old-{layout}.bin"
    write_dataflash(path, run, layout)
    table = read_input(path)
    assert np.abs(table.mag - run.mag_ut).max() <= 0.05 + 1e-9  # milligauss rounding
    t_s = table.numeric("t_s")
    assert np.abs((t_s - t_s[0]) - run.t_s).max() < 2e-3  # TimeMS: whole ms
    assert np.abs(table.acc - run.acc_ms2).max() < 1e-4
    out = tmp_path / "cal.json"
    assert main(["fit", str(path), "--method", "ellipsoid", "--field-ut", "50", "--out", str(out)]) == 0
    assert out.exists() and "Traceback" not in capsys.readouterr().err


def test_a_mag_layout_without_a_field_is_one_clear_line(tmp_path: Path, capsys) -> None:
    path = tmp_path / "odd.bin"
    write_dataflash(path, simulated_run(count=60, rate_hz=25.0), "unknown")
    assert "unknown" in DATAFLASH_MAG_LAYOUTS
    assert main(["fit", str(path), "--out", str(tmp_path / "cal.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "MAG record layout magnet does not know (TimeMS,FldX,FldY,FldZ)" in err[0], err


# ----------------------------------------------------------------------------------------------------------- tlog


def test_tlog_written_by_pymavlink_is_read_back(tlog: tuple[Path, object]) -> None:
    path, run = tlog
    for instance, message in ((0, "RAW_IMU"), (1, "SCALED_IMU2")):
        table = read_input(path, InputOptions(mag=instance))
        assert message in table.note and "system 7" in table.note
        assert np.abs(table.mag - run.mag_ut).max() <= 0.05 + 1e-9  # milligauss rounding
        assert np.abs(table.acc - run.acc_ms2).max() < 0.01
        assert np.abs(np.column_stack([table.numeric(c) for c in ("gx", "gy", "gz")]) - run.gyr_rads).max() < 1e-3
        assert table.numeric("current_a") == pytest.approx(12.5)
        assert table.numeric("throttle") == pytest.approx(0.4)
    with pytest.raises(ValueError, match=r"no magnetometer instance 2 in this log \(instances: \[0, 1\]\)"):
        read_input(path, InputOptions(mag=2))


def test_tlog_fit_heading_compare_and_replay(tlog: tuple[Path, object], tmp_path: Path, capsys) -> None:
    path, run = tlog
    cal = tmp_path / "cal.json"
    assert main(["fit", str(path), "--method", "ellipsoid", "--field-ut", "50", "--out", str(cal)]) == 0
    assert main(["heading", str(path), "--calibration", str(cal), "--compare"]) == 0
    err = capsys.readouterr().err
    assert float(COMPARE.search(err).group(1)) < 0.5  # type: ignore[union-attr]
    assert "magnet fit: MAVLink telemetry: RAW_IMU" in err and "magnet heading: MAVLink telemetry: RAW_IMU" in err
    assert len(read_recording(path)) == len(run.t_s)
    from services.report.data import load_samples

    samples = load_samples(path, None, InputOptions(mag=1), "report")  # what magnet report draws, without drawing
    assert len(samples.raw) == len(run.t_s)
    assert "magnet report: MAVLink telemetry: SCALED_IMU2" in capsys.readouterr().err


# ------------------------------------------------------------------------------------------------------ bad input


def _refused(capsys: pytest.CaptureFixture[str], *args: str) -> str:
    assert main(list(args)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    return err


def test_bad_logs_are_one_clear_line_and_nothing_is_written(tmp_path: Path, capsys) -> None:
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(PX4_LOG.read_bytes()[:500])
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(np.random.default_rng(0).bytes(4000))
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    silent = tmp_path / "no_imu.tlog"
    write_tlog(silent, simulated_run(), with_imu=False, count=50)
    out = tmp_path / "cal.json"
    cases = {
        cut: "no logged data",
        garbage: "not an ArduPilot DataFlash log",
        empty: "the file is empty",
        silent: "holds no magnetometer",
    }
    for path, words in cases.items():
        err = _refused(capsys, "fit", str(path), "--method", "ellipsoid", "--out", str(out))
        assert words in err and str(path) in err
    assert "no magnetometer instance 5" in _refused(capsys, "heading", str(PX4_LOG), "--mag", "5")
    assert not out.exists()


def test_px4_versions_before_1_12_log_sensor_mag_calibrated() -> None:
    """ver_sw_release is 0xAABBCCTT; pyulog's small sample (v1.11.2) logs sensor_mag equal to vehicle_magnetometer
    (checked by hand), so only v1.12 and later are read as raw."""
    from services.common.inputs.ulog import RAW_SENSOR_MAG_SINCE, px4_version

    assert px4_version(0x010B0200) == (1, 11) < RAW_SENSOR_MAG_SINCE
    assert px4_version(0x010F0000) == (1, 15) >= RAW_SENSOR_MAG_SINCE
    assert px4_version(0) is None


class _Dataset:
    def __init__(self, name: str, multi_id: int, data: dict[str, np.ndarray]) -> None:
        self.name, self.multi_id, self.data = name, multi_id, data


class _ULog:
    """What the ULog reader uses of pyulog's parse: a PX4 1.14 log with two raw magnetometers."""

    def __init__(self, params: dict[str, float], raw: np.ndarray) -> None:
        t = np.arange(len(raw), dtype=np.uint64) * 10_000
        fields = {"timestamp": t, "x": raw[:, 0], "y": raw[:, 1], "z": raw[:, 2]}
        self.data_list = [
            _Dataset("sensor_mag", 0, {**fields, "device_id": np.full(len(raw), 1111)}),
            _Dataset("sensor_mag", 1, {**fields, "device_id": np.full(len(raw), 2222)}),
        ]
        self.initial_parameters = params
        self.msg_info_dict = {"ver_sw_release": 0x010E00FF}
        self.message_formats: dict[str, object] = {}


def test_px4_raw_sensor_mag_is_turned_into_the_body_frame_as_px4_rotates_it() -> None:
    """PX4 (calibration::Magnetometer) rotates a corrected reading by CAL_MAGn_ROT for an external magnetometer and
    by the board rotation (SENS_BOARD_ROT) for an internal one (CAL_MAGn_ROT = -1); yaw 90 takes x to y."""
    from services.common.inputs.ulog import _mag

    raw = np.array([[0.3, 0.0, 0.4], [0.0, 0.2, 0.5]])  # gauss, the board's axes
    params = {"CAL_MAG0_ID": 2222, "CAL_MAG0_ROT": 2, "CAL_MAG1_ID": 1111, "CAL_MAG1_ROT": -1, "SENS_BOARD_ROT": 4}
    external, note = _mag(_ULog(params, raw), Path("x.ulg"), 1)
    assert "raw, uncalibrated" in note and "CAL_MAG0_ROT=2" in note
    assert external.values == pytest.approx(np.array([[0.0, 30.0, 40.0], [-20.0, 0.0, 50.0]]))  # yaw 90, in uT
    internal, note = _mag(_ULog(params, raw), Path("x.ulg"), 0)
    assert "SENS_BOARD_ROT=4" in note
    assert internal.values == pytest.approx(np.array([[-30.0, 0.0, 40.0], [0.0, -20.0, 50.0]]))  # yaw 180


class _Record:
    """A DataFlash record as pymavlink gives it: attributes and get_fieldnames()."""

    def __init__(self, **fields: float) -> None:
        self.__dict__.update(fields)
        self._names = list(fields)

    def get_fieldnames(self) -> list[str]:
        return self._names


def test_current_dataflash_instances_use_the_i_field_and_their_own_parameters() -> None:
    """Instance 1 is corrected with COMPASS_DIA2_*, COMPASS_ODI2_* and COMPASS_SCALE2 (applied: within 0.85..1.4)."""
    from services.common.inputs.dataflash import KEPT_FIELDS, _mag
    from services.common.inputs.flightlogs import Table

    raw = np.array([100.0, -200.0, 300.0])  # mGauss
    ofs, mot = np.array([-20.0, 10.0, 5.0]), np.array([1.0, 2.0, 3.0])
    params = {"COMPASS_DIA2_X": 1.1, "COMPASS_DIA2_Y": 0.9, "COMPASS_DIA2_Z": 1.0, "COMPASS_ODI2_X": 0.05}
    params.update({"COMPASS_ODI2_Y": 0.0, "COMPASS_ODI2_Z": -0.02, "COMPASS_SCALE2": 1.2, "COMPASS_SCALE": 3.0})
    matrix = np.array([[1.1, 0.05, 0.0], [0.05, 0.9, -0.02], [0.0, -0.02, 1.0]])
    logged = matrix @ (1.2 * (raw + ofs)) + mot
    fields = dict(
        zip(("MagX", "MagY", "MagZ", "OfsX", "OfsY", "OfsZ", "MOfsX", "MOfsY", "MOfsZ"), [*logged, *ofs, *mot])
    )
    records = Table.of(KEPT_FIELDS["MAG"], [_Record(TimeUS=t, I=i, **fields) for t in (1e6, 2e6) for i in (0, 1)])
    stream, note = _mag(Path("x.bin"), {"MAG": records}, params, 1)
    assert stream.values == pytest.approx(np.tile(raw / 10, (2, 1)))  # uT
    assert "COMPASS_DIA2_*=[1.1, 0.9, 1.0]" in note and "scale 1.2" in note
    with pytest.raises(ValueError, match=r"instances: \[0, 1\]"):
        _mag(Path("x.bin"), {"MAG": records}, params, 2)
