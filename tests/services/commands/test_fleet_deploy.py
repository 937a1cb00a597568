"""deploy/site: every unit's command line is one `magnet` accepts, and the example fleet file parses."""

from __future__ import annotations

import re
import shlex

import pytest
from helpers import REPO_ROOT

from magnet.fleet.places import parse_places
from services.cli import build_parser

SITE = REPO_ROOT / "deploy" / "site"
ENV = {"SENSOR": "hmc5883l", "BUS": "1", "ADDRESS": "0x1e", "RATE": "50", "LOCATION": "50.45,30.52,180"}
UNITS = sorted(SITE.glob("*/*.service"))


def test_the_site_has_a_unit_for_each_host():
    assert {unit.parent.name for unit in UNITS} == {"router", "edge", "services"}


@pytest.mark.parametrize("unit", UNITS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_each_units_command_is_one_magnet_accepts(unit):
    line = next(line for line in unit.read_text().splitlines() if line.startswith("ExecStart="))
    command = re.sub(r"\$\{(\w+)\}", lambda m: ENV[m.group(1)], line.removeprefix("ExecStart=")).replace("%i", "mast-1")
    program, *argv = shlex.split(command)
    assert program == "/opt/magnet/.venv/bin/magnet"
    args = build_parser(argv).parse_args(argv)
    assert args.config.startswith("/etc/magnet/tls/")
    if args.command in ("calibrator", "compass"):
        assert str(args.fleet) == "/etc/magnet/fleet.json5"


def test_the_example_fleet_file_parses():
    fleet = parse_places((SITE / "services" / "fleet.json5").read_text())
    assert fleet["buoy-7"].location.lat_deg == -33.86 and fleet["spare-3"].location is None
