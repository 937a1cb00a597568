"""Values that start with a minus: a southern place or a negative first component is a value, not an option."""

from __future__ import annotations

import pytest

from services.cli import build_parser


def _parsed(*argv: str):
    return build_parser(list(argv)).parse_args(list(argv))


def test_a_southern_place_is_read_as_the_value_of_location():
    args = _parsed("heading", "walk.csv", "--location", "-33.87,151.21", "--date", "2026-01-01")
    assert args.location == "-33.87,151.21"


def test_a_negative_first_component_of_a_list_is_a_value():
    args = _parsed("sample", "--sensor", "hmc5883l", "--hard-iron", "-25,40,12")
    assert args.hard_iron_ut == "-25,40,12"


def test_an_unknown_option_is_still_refused(capsys):
    with pytest.raises(SystemExit) as stopped:
        _parsed("heading", "walk.csv", "-x")
    assert stopped.value.code == 2
    assert "unrecognized arguments: -x" in capsys.readouterr().err
