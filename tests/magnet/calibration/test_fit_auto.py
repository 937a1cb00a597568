"""``auto`` (``magnet.calibration.choose``): gyro-ellipsoid or ellipsoid, whichever the gate finds better; the
record names the real method, says what the other scored, and round-trips through the file, the wire, the store and
a signature."""

from __future__ import annotations

import json

import numpy as np
import pytest

from magnet import signing, wire
from magnet.calibration import AUTO, FitError, FitInput, Method, fit, fit_auto, parse_choice
from magnet.calibration.choose import _choose
from magnet.model import KNOWN_METHODS, Calibration
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate
from services.calibrator.store import CalibrationStore
from services.cli import main

RATE_HZ = 100.0
PERIOD_S = 1.0 / RATE_HZ
LATE = 3  # samples: the magnetometer reads 30 ms after the gyroscope


@pytest.fixture(scope="module")
def late_run():
    """40 s of a fast tumble at 100 Hz, hard and soft iron, the magnetometer 30 ms late behind the gyroscope."""
    rng = np.random.default_rng(21)
    errors = SensorErrors.random(
        rng, 50.0, hard_iron_max_ratio=0.5, soft_iron_max=0.05, noise_ut=0.2, gyro_noise_rads=0.002
    )
    run = simulate(
        SimulatorConfig(trajectory=Trajectory.FAST_TUMBLE, rate_hz=RATE_HZ, count=4000, errors=errors, seed=3)
    )
    late = np.vstack([np.repeat(run.mag_ut[:1], LATE, axis=0), run.mag_ut[:-LATE]])
    return run, late


@pytest.fixture(scope="module")
def chosen(late_run):
    run, late = late_run
    return fit_auto(
        FitInput(late, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=PERIOD_S, field_ut=run.earth.total_ut)
    )


def test_a_late_magnetometer_with_a_gyroscope_gets_gyro_ellipsoid_and_the_record_says_why(late_run, chosen):
    run, late = late_run
    plain = fit(
        FitInput(late, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=PERIOD_S, field_ut=run.earth.total_ut),
        "ellipsoid",
    )
    assert chosen.accepted, chosen.reason
    assert chosen.method == "gyro-ellipsoid"
    other = chosen.quality["auto_other"]
    assert other["method"] == "ellipsoid" and other["accepted"] == plain.accepted
    assert other["holdout_consistency_deg"] == pytest.approx(plain.quality["holdout_consistency_deg"])
    if plain.accepted:  # both accepted: the lower held-out consistency won
        assert chosen.quality["holdout_consistency_deg"] < other["holdout_consistency_deg"]
    assert "chosen by auto" in chosen.reason
    assert chosen.quality["mag_lag_s"] == pytest.approx(LATE * PERIOD_S, abs=0.005)


def test_the_chosen_record_round_trips_through_file_wire_store_and_signature(chosen, tmp_path):
    again = Calibration.from_dict(json.loads(json.dumps(chosen.to_dict())))
    assert again.method == "gyro-ellipsoid" and again.quality["auto_other"] == chosen.quality.to_dict()["auto_other"]
    decoded = wire.decode_calibration(wire.encode_calibration("dev-1", chosen, 5))
    assert decoded.calibration.quality["auto_other"]["method"] == "ellipsoid"
    private_pem, public_pem = signing.new_key_pair()
    signed = signing.Signer(signing.load_private_key(private_pem)).sign(decoded.to_record())
    trusted = signing.TrustedKeys([signing.load_public_key(public_pem)])
    assert trusted.verify(json.loads(json.dumps(signed)))  # as a JSON reader gets it
    with CalibrationStore(tmp_path / "c.db") as store:
        assert store.save(decoded)
        stored = store.latest("dev-1")
    assert stored is not None and stored.calibration.quality["auto_other"] == decoded.calibration.quality["auto_other"]


def test_without_a_gyroscope_auto_is_the_ellipsoid_fit():
    errors = SensorErrors(hard_iron_ut=(8.0, -3.0, 5.0), noise_ut=0.2)
    run = simulate(SimulatorConfig(trajectory=Trajectory.TUMBLE, rate_hz=50.0, count=1500, errors=errors))
    auto = fit_auto(FitInput(run.mag_ut, acc=run.acc_ms2))
    plain = fit(FitInput(run.mag_ut, acc=run.acc_ms2), "ellipsoid")
    assert auto.method == "ellipsoid" and auto.accepted, auto.reason
    np.testing.assert_array_equal(auto.offset, plain.offset)
    assert auto.reason == plain.reason and "auto_other" not in auto.quality.extra
    # a gyroscope without its sample period is no gyroscope either
    assert fit_auto(FitInput(run.mag_ut, acc=run.acc_ms2, gyr_rads=run.gyr_rads)).method == "ellipsoid"


def test_a_gyro_ellipsoid_that_cannot_be_computed_leaves_the_ellipsoid(late_run):
    run, _ = late_run
    still = np.zeros_like(run.gyr_rads)  # no turn at all: the gyroscope does not determine the calibration
    with pytest.raises(FitError, match="every axis"):
        fit(FitInput(run.mag_ut, gyr_rads=still, period_s=PERIOD_S), "gyro-ellipsoid")
    record = fit_auto(FitInput(run.mag_ut, gyr_rads=still, period_s=PERIOD_S))
    assert record.method == "ellipsoid" and record.accepted, record.reason
    other = record.quality["auto_other"]
    assert other["method"] == "gyro-ellipsoid" and other["accepted"] is False and "every axis" in other["error"]
    assert "gyro-ellipsoid was refused" in record.reason


def test_refused_by_both_says_both_reasons_and_stays_gyro_ellipsoid(late_run):
    run, late = late_run
    record = fit_auto(
        FitInput(late, acc=run.acc_ms2, gyr_rads=run.gyr_rads, period_s=PERIOD_S, field_ut=25.0)
    )  # half the field
    assert not record.accepted and record.method == "gyro-ellipsoid"
    assert "gyro-ellipsoid refused:" in record.reason and "ellipsoid refused:" in record.reason
    gyro_part, plain_part = record.reason.split(" | ")
    assert "fitted radius" in gyro_part and "fitted radius" in plain_part  # each method's own refusal
    assert record.quality["auto_other"]["accepted"] is False
    with pytest.raises(FitError, match=r"gyro-ellipsoid refused: only 20 samples.*ellipsoid refused: only 20"):
        fit_auto(FitInput(late[:20], gyr_rads=run.gyr_rads[:20], period_s=PERIOD_S))


def test_both_accepted_the_lower_held_out_consistency_wins_a_tie_goes_to_gyro_ellipsoid(chosen):
    def scored(method: Method, figure: float, accepted: bool = True) -> Calibration:
        quality = chosen.quality.with_extra(holdout_consistency_deg=figure)
        return chosen.replace(method=method.value, quality=quality, accepted=accepted)

    gyro = scored(Method.GYRO_ELLIPSOID, 0.8)
    assert _choose({Method.GYRO_ELLIPSOID: gyro, Method.ELLIPSOID: scored(Method.ELLIPSOID, 0.5)}).value == "ellipsoid"
    tie = {Method.GYRO_ELLIPSOID: gyro, Method.ELLIPSOID: scored(Method.ELLIPSOID, 0.8)}
    assert _choose(tie) is Method.GYRO_ELLIPSOID
    refused = {Method.GYRO_ELLIPSOID: gyro, Method.ELLIPSOID: scored(Method.ELLIPSOID, 0.5, accepted=False)}
    assert _choose(refused) is Method.GYRO_ELLIPSOID


def test_auto_is_a_choice_never_a_method_a_record_may_name():
    assert parse_choice(" Auto ") == AUTO and parse_choice("ELLIPSOID") == "ellipsoid"
    assert AUTO not in KNOWN_METHODS
    with pytest.raises(ValueError, match="auto, minmax2d"):
        parse_choice("best")
    with pytest.raises(ValueError):
        Calibration.from_dict({"method": "auto", "offset": [0, 0, 0], "matrix": np.eye(3).tolist()})


def test_magnet_fit_chooses_by_default(late_run, tmp_path, capsys):
    run, late = late_run
    table = np.hstack([run.t_s[:, None], late, run.acc_ms2, run.gyr_rads])
    path = tmp_path / "late.csv"
    header = "t_s,mx,my,mz,ax,ay,az,gx,gy,gz"
    np.savetxt(path, table, delimiter=",", header=header, comments="", fmt="%.9g")
    out = tmp_path / "cal.json"
    assert main(["fit", str(path), "--field-ut", f"{run.earth.total_ut:.3f}", "--out", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["method"] == "gyro-ellipsoid" and record["quality"]["auto_other"]["method"] == "ellipsoid"
    assert main(["fit", str(path), "--field-ut", "25", "--out", str(tmp_path / "no.json")]) == 1
    err = capsys.readouterr().err
    assert "gyro-ellipsoid refused:" in err and "ellipsoid refused:" in err
    with pytest.raises(SystemExit) as refused:  # argparse: one usage line, exit 2
        main(["fit", str(path), "--method", "best"])
    assert refused.value.code == 2
