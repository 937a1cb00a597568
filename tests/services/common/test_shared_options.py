"""The option groups several commands share, declared once: a recording's stream (``--mag``, ``--topic``) and a
MAVLink link (``--mavlink``/``--apply`` URL, ``--baud``)."""

from __future__ import annotations

import argparse

import pytest

from services.common.inputs import add_input_arguments
from services.common.inputs.input_options import InputOptions
from services.common.mavlink_options import DEFAULT_BAUD, add_mavlink_url_arguments, check_baud, check_url


def _inputs(*argv: str) -> InputOptions:
    parser = argparse.ArgumentParser()
    add_input_arguments(parser)
    return InputOptions.from_args(parser.parse_args(list(argv)))


def test_a_recording_s_stream_options() -> None:
    assert _inputs() == InputOptions() == InputOptions(None, None)
    assert _inputs("--mag", "2", "--topic", "/a/mag") == InputOptions(2, "/a/mag")
    assert InputOptions.from_args(argparse.Namespace()) == InputOptions()  # a command without them


@pytest.mark.parametrize(
    "argv,message",
    [(["--mag", "x"], "--mag: invalid literal for int()"), (["--mag", "-1"], "--mag must be a whole number >= 0")],
)
def test_a_bad_stream_option_names_its_flag(argv: list[str], message: str) -> None:
    with pytest.raises(ValueError) as exc:
        _inputs(*argv)
    assert message in str(exc.value)


@pytest.mark.parametrize(
    "url,problem",
    [
        ("udpin:127.0.0.1:14550", None),
        ("tcp:localhost:5760", None),
        ("/dev/ttyACM0", None),
        (None, None),
        ("", "needs a URL"),
        ("udpin:127.0.0.1", "expects udpin:HOST:PORT"),
        ("udpout::14550", "expects udpout:HOST:PORT"),
        ("tcp:h:99999", "port in 1..65535"),
        ("bogus:thing", "unknown link kind 'bogus'"),  # pymavlink would fail on int('thing')
        ("COM3", None),
    ],
)
def test_a_mavlink_url_is_checked(url: str | None, problem: str | None) -> None:
    found = check_url(url)
    assert (found is None) if problem is None else (found is not None and problem in found)


def test_the_baud_rate_default_and_check_are_written_once() -> None:
    assert check_baud(DEFAULT_BAUD) is None and check_baud(115200) is None
    assert check_baud(49) == check_baud(True) == "must be 50..10000000"
    parser = argparse.ArgumentParser()
    add_mavlink_url_arguments(parser, "--apply", "a vehicle", "its baud rate")
    args = parser.parse_args(["--apply", "udpin:127.0.0.1:1"])
    assert (args.apply, args.baud) == ("udpin:127.0.0.1:1", DEFAULT_BAUD)
