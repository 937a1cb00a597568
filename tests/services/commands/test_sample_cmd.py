"""``magnet sample`` and ``magnet selftest`` through the command table, emulated."""

import csv
import io

import numpy as np
import pytest

from magnet.drivers import SensorReadError, open_sensor
from magnet.emulators.base import ConstantSource, FaultInjector
from magnet.emulators.hmc5883l import HMC5883LEmulator
from services.cli import main
from services.commands.sample import GIVE_UP_AFTER, SampleSettings, read_loop


def run_cli(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize(
    "sensor,acc", [("hmc5883l", False), ("qmc5883l", False), ("lsm303dlh", True), ("ak09918c+bma456", True)]
)
def test_sample_emulated_csv_parses(capsys, sensor, acc):
    code, out, _ = run_cli(
        capsys,
        "sample",
        "--sensor",
        sensor,
        "--emulate",
        "--count",
        "40",
        "--trajectory",
        "spin",
        "--noise-ut",
        "0.2",
        "--seed",
        "3",
    )
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    assert len(rows) == 40
    expected = (
        ["t_s", "mx", "my", "mz"] + (["ax", "ay", "az"] if acc else []) + ["true_heading_deg", "pitch_deg", "roll_deg"]
    )
    assert list(rows[0]) == expected
    mag = np.array([[float(r[k]) for k in ("mx", "my", "mz")] for r in rows])
    assert 20 < np.median(np.linalg.norm(mag, axis=1)) < 70  # an Earth-sized field in uT
    heading = np.radians([float(r["true_heading_deg"]) for r in rows])
    assert np.ptp(np.unwrap(heading)) > np.radians(300)  # a level spin goes all the way round


def test_sample_is_reproducible_and_seed_matters(capsys):
    args = ("sample", "--sensor", "hmc5883l", "--emulate", "--count", "10", "--noise-ut", "0.5")
    first = run_cli(capsys, *args, "--seed", "1")[1]
    again = run_cli(capsys, *args, "--seed", "1")[1]
    other = run_cli(capsys, *args, "--seed", "2")[1]
    assert first == again and first != other


def test_sample_turntable_feeds_fit(capsys, tmp_path):
    code, out, err = run_cli(
        capsys,
        "sample",
        "--sensor",
        "lsm303dlh",
        "--emulate",
        "--count",
        "48",
        "--trajectory",
        "turntable",
        "--hard-iron",
        "5,-3,2",
    )
    assert code == 0 and "--horizontal" in err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert {r["mounting"] for r in rows} == {"a", "b"}
    assert {float(r["heading_deg"]) % 30 for r in rows} == {0.0}


def test_sample_bad_input_is_one_line(capsys):
    code, _, err = run_cli(capsys, "sample", "--sensor", "hmc5883l", "--emulate", "--trajectory", "loop")
    assert code == 2 and "unknown --trajectory 'loop'" in err
    code, _, err = run_cli(capsys, "sample", "--sensor", "hmc5883l")
    assert code == 2 and "--bus" in err


def test_sample_gives_up_on_a_dead_bus_with_a_clear_error_after_bounded_backoff():
    faults = FaultInjector()
    sensor = open_sensor("hmc5883l", HMC5883LEmulator(ConstantSource(), faults=faults), sleep=lambda s: None)
    faults.probability = 1.0  # the bus dies after set-up
    slept = []
    loop = read_loop(sensor, SampleSettings(sensor="hmc5883l", emulate=True), sleep=slept.append)
    with pytest.raises(SensorReadError, match=f"no usable reading after {GIVE_UP_AFTER} failures in a row"):
        loop.next()
    assert loop.health.errors == loop.health.attempts == GIVE_UP_AFTER
    assert len(slept) == GIVE_UP_AFTER - 1 and max(slept) <= 1.0 and slept == sorted(slept)


@pytest.mark.parametrize(
    "argv,message",
    [
        (("--rate", "0"), "--rate must be > 0"),
        (("--orientation", "sideways"), "unknown orientation 'sideways'"),
        (("--hard-iron", "1,2"), "--hard-iron: needs 3 numbers"),
        (("--location", "999,0"), "latitude"),
    ],
)
def test_sample_settings_are_checked_before_anything_runs(capsys, argv, message):
    code, out, err = run_cli(capsys, "sample", "--sensor", "hmc5883l", "--emulate", *argv)
    assert code == 2 and message in err and out == "" and len(err.strip().splitlines()) == 1


def test_selftest_emulated_corrects_gain_error(capsys):
    code, out, _ = run_cli(capsys, "selftest", "--emulate", "--gain-error", "0.05,-0.03,0.02")
    assert code == 0 and "passed" in out
    scales = [float(line.split("scale")[1]) for line in out.splitlines() if "scale " in line and ":" in line[:4]]
    assert np.allclose(scales, 1 / (1 + np.array([0.05, -0.03, 0.02])), rtol=3e-3)
    code, out, _ = run_cli(capsys, "selftest", "--emulate", "--gain-error", "0,-0.6,0")
    assert code == 1 and "FAILED" in out
