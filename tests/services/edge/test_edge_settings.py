"""``magnet edge``'s settings, declared once: every flag keeps its name and default, each bad value is refused with a
message naming its flag, and the settings built in code are checked the same way."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from services.common.ros2_options import Ros2Settings, add_ros2_arguments
from services.common.sim_options import SimulatorSettings
from services.edge.settings import EdgeSettings, SourceKind, add_arguments


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser


def _settings(*argv: str) -> EdgeSettings:
    return EdgeSettings.from_args(_parser().parse_args(list(argv)))


def test_the_defaults_are_the_dataclass_s_alone() -> None:
    assert _settings("--emulate") == EdgeSettings(emulate=True)


def test_vehicle_names_the_vehicle_its_devices_are_compasses_of() -> None:
    assert _settings("--emulate").vehicle == "" and _settings("--emulate", "--vehicle", "rover7").vehicle == "rover7"
    with pytest.raises(ValueError, match="--vehicle"):
        _settings("--emulate", "--vehicle", "a/b")


def test_every_flag_keeps_its_name_and_default() -> None:
    """The flags are contracts (README, docs, magnet up, tests): these are the defaults they had."""
    settings = _settings("--emulate")
    expected = {
        "device": "dev",
        "sensor": "sim",
        "rate_hz": 50.0,
        "batch": 10,
        "duration_s": None,
        "devices": 0,
        "trajectory_samples": 3000,
        "speedup": 1.0,
        "speed": 1.0,
        "emulate_faults": 0.0,
        "wire_version": 2,
        "baud": 57600,
        "device_prefix": "mav",
        "vehicle_timeout_s": 3.0,
    }
    assert {name: getattr(settings, name) for name in expected} == expected
    assert (settings.simulator.seed, settings.simulator.noise_ut) == (1, 0.3)  # the edge's own, not sample's
    assert settings.ros2 == Ros2Settings() and settings.source_kind is SourceKind.SIMULATOR
    assert str(settings.location) == "50.45,30.52,0"
    help_text = _parser().format_help()
    for flag in (
        "--device", "--sensor", "--bus", "--address", "--emulate", "--devices", "--rate", "--batch", "--duration",
        "--gyro", "--wire", "--seed", "--trajectory", "--hard-iron", "--soft-iron", "--noise-ut", "--gyro-bias",
        "--gyro-noise", "--location", "--date", "--trajectory-samples", "--speedup", "--emulate-faults", "--replay",
        "--speed", "--mavlink", "--baud", "--device-prefix", "--vehicle-timeout", "--ros2", "--ros-domain",
        "--ros-namespace", "--mag-topic", "--mag", "--imu-topic", "--prefix", "--connect", "--listen",
    ):  # fmt: skip
        assert f"{flag} " in help_text or f"{flag}\n" in help_text, flag


def test_options_are_parsed() -> None:
    got = _settings(
        "--sensor", "hmc5883l", "--bus", "1", "--address", "0x1e", "--rate", "20", "--duration", "2.5", "--wire", "1"
    )
    assert (got.bus, got.address, got.rate_hz, got.duration_s, got.wire_version) == (1, 0x1E, 20.0, 2.5, 1)
    assert got.source_kind is SourceKind.CHIP and got.location is None
    assert _settings("--ros2", "--mag-topic", "/m", "--ros-domain", "7").ros2 == Ros2Settings(True, 7)
    replay = _settings("--replay", "r.ulg", "--mag", "1", "--location", "10,20,30")
    assert replay.mag_instance == 1 and replay.location is not None and replay.location.alt_m == 30.0


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--device", "a/b"], "--device is not a device id"),
        (["--sensor", "nope"], "--sensor must be one of"),
        (["--bus", "x"], "--bus: invalid literal"),
        (["--address", "zz"], "--address: invalid literal"),
        (["--devices", "-1"], "--devices must be 0..100000, got -1"),
        (["--rate", "0"], "--rate must be in (0, 100000] Hz, got 0.0"),
        (["--batch", "0"], "--batch must be 1..10000, got 0"),
        (["--duration", "-1"], "--duration must be >= 0 seconds, got -1.0"),
        (["--wire", "3"], "--wire must be one of 1, 2, got 3"),
        (["--trajectory-samples", "0"], "--trajectory-samples must be a whole number >= 1, got 0"),
        (["--speedup", "0"], "--speedup must be in (0, 1000], got 0.0"),
        (["--emulate-faults", "2"], "--emulate-faults must be a probability in [0, 1], got 2.0"),
        (["--speed", "0"], "--speed must be in (0, 1000], got 0.0"),
        (["--mavlink", "udpin:host"], "--mavlink expects udpin:HOST:PORT with a port in 1..65535"),
        (["--mavlink", "udpin:h:1", "--baud", "1"], "--baud must be 50..10000000, got 1"),
        (["--mavlink", "udpin:h:1", "--device-prefix", "a/b"], "--device-prefix is not a device id"),
        (["--mavlink", "udpin:h:1", "--vehicle-timeout", "0"], "--vehicle-timeout must be in (0, 3600] seconds"),
        (["--ros2", "--mag-topic", "m", "--ros-domain", "300"], "--ros-domain must be a whole number from 0 to 232"),
        (["--ros2", "--mag-topic", "m", "--ros-namespace", "x"], "--ros-namespace is not a ROS namespace"),
        (["--replay", "r.csv", "--mag", "x"], "--mag: invalid literal"),
        (["--imu-topic", "i"], "--mag-topic and --imu-topic need --ros2"),
        (["--seed", "x"], "argument --seed: invalid int value"),
        (["--trajectory", "loop"], "--trajectory: unknown --trajectory 'loop'"),
        (["--hard-iron", "1,2"], "--hard-iron: needs 3 numbers, got 2"),
        (["--soft-iron", "1,2"], "--soft-iron: needs 3 or 9 numbers, got 2"),
        (["--noise-ut", "-1"], "--noise-ut must be >= 0, got -1.0"),
        (["--gyro-bias", "a,b,c"], "--gyro-bias: must be comma-separated numbers"),
        (["--gyro-noise", "-1"], "--gyro-noise must be >= 0, got -1.0"),
        (["--location", "999,0"], "--location: latitude must be within -90..90 degrees"),
        (["--replay", "r.csv", "--emulate"], "--replay plays a recording: it takes no --emulate"),
        (["--mavlink", "udpin:h:1", "--emulate"], "--mavlink reads vehicles: it takes no --emulate"),
        (["--ros2"], "a ROS 2 source needs --ros2 and --mag-topic"),
        (["--devices", "3"], "--devices needs --emulate"),
        (["--sensor", "hmc5883l"], "a real sensor needs --bus N"),
        (["--emulate", "--emulate-faults", "0.5"], "--emulate-faults needs --emulate and a chip"),
    ],
)
def test_each_bad_option_is_refused_naming_its_flag(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises((ValueError, SystemExit)) as exc:
        _settings(*argv)
    text = str(exc.value) if exc.type is ValueError else capsys.readouterr().err
    assert message in text


def test_settings_built_in_code_are_checked_the_same_way() -> None:
    with pytest.raises(ValueError, match=r"--rate must be in \(0, 100000\] Hz"):
        EdgeSettings(emulate=True, rate_hz=0.0)
    with pytest.raises(ValueError, match="--noise-ut must be >= 0"):
        SimulatorSettings(noise_ut=-1.0)
    with pytest.raises(ValueError, match="--ros-domain"):
        Ros2Settings(domain=-1)


def test_the_ros2_group_says_what_ros2_does_in_the_command() -> None:
    parser = argparse.ArgumentParser()
    add_ros2_arguments(parser, "publish the headings as ROS 2 topics")
    assert "--ros2: publish the headings as ROS 2 topics" in parser.format_help()
    assert Ros2Settings.from_args(parser.parse_args(["--ros2", "--ros-namespace", "/a"])) == Ros2Settings(True, 0, "/a")


def test_each_source_declares_its_own_options_once():
    from services.edge import settings as edge_settings

    groups = (
        edge_settings.CommonOptions,
        edge_settings.ChipOptions,
        edge_settings.FleetOptions,
        edge_settings.SimulatorOptions,
        edge_settings.ReplayOptions,
        edge_settings.MavlinkOptions,
        edge_settings.Ros2SourceOptions,
    )
    declared = [f.name for group in groups for f in dataclasses.fields(group)]
    assert len(declared) == len(set(declared))  # no option in two sources' groups
    nested = {"simulator", "ros2", "zenoh"}
    assert set(declared) == {f.name for f in dataclasses.fields(EdgeSettings)} - nested
    assert set(edge_settings.SOURCE_OPTIONS) == set(SourceKind)  # every kind has its options and its check
    assert _settings("--mavlink", "udpin:127.0.0.1:14550").source_kind is SourceKind.MAVLINK
    with pytest.raises(ValueError, match="--mavlink reads vehicles"):
        _settings("--mavlink", "udpin:127.0.0.1:14550", "--emulate")  # the MAVLink source's own check
