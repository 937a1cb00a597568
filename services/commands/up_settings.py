"""The settings of ``magnet up``, checked in one place before anything starts."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from magnet import wire
from magnet.drift import DEFAULT_DRIFT, DriftSettings
from magnet.earth.location import Location
from magnet.simulator import DEFAULT_LOCATION
from services.common.options import add_options, check_options, from_args, option
from services.common.places_options import add_drift_arguments, drift_from_args
from services.common.sim_options import SimulatorSettings
from services.edge.settings import EdgeSettings

MAX_DEVICES = 10_000


def _devices(value: int) -> str | None:
    return None if 1 <= value <= MAX_DEVICES else f"must be 1..{MAX_DEVICES}"


def _duration(value: float | None) -> str | None:
    return None if value is None or value >= 0 else "must be >= 0 seconds"


def _interval(value: float | None) -> str | None:
    return None if value is None or value > 0 else "must be > 0 seconds"


@dataclasses.dataclass(frozen=True)
class UpSettings:
    """What ``magnet up`` runs, checked in one place before anything starts: each option's own check, the edge's
    (rate, batch, speedup) through the ``EdgeSettings`` it will run, the location through ``Location.parse``, the
    dashboard's address through ``parse_http``."""

    devices: int = option(4, "--devices", help="emulated devices", check=_devices)
    rate_hz: float = option(50.0, "--rate", help="samples per second per device")
    batch: int = option(10, "--batch", help="samples per message")
    speedup: float = option(4.0, "--speedup", help="the emulated devices tumble this many times faster than real time")
    location: str = option(
        DEFAULT_LOCATION, "--location", help="LAT,LON[,ALT_M] of the devices (default Kyiv)", show_default=False
    )
    db: Path | None = option(None, "--db", parse=Path, help="calibration database (default: a temporary directory)")
    duration_s: float | None = option(
        None, "--duration", parse=float, check=_duration, help="stop after this many seconds"
    )
    interval_s: float | None = option(
        None,
        "--interval",
        parse=float,
        check=_interval,
        help="seconds between views (default 0.5 on a terminal, else 3)",
    )
    prefix: str = option(wire.DEFAULT_PREFIX, "--prefix", help="key prefix")
    http: str | None = option(
        None,
        "--http",
        metavar="HOST:PORT",
        help="where the dashboard serves its page (default 127.0.0.1:8080, or a free port when taken)",
    )
    dashboard: bool = option(True, "--dashboard", negate="--no-dashboard", help="do not start the web dashboard")
    drift: DriftSettings | None = DEFAULT_DRIFT  # the compass's drift alerts (None: --no-drift)

    def __post_init__(self) -> None:
        if self.http is not None:
            from services.dashboard.settings import parse_http

            parse_http(self.http)
        check_options(self)
        wire.validate_prefix(self.prefix)
        try:
            place = Location.parse(self.location)
        except ValueError as exc:
            raise ValueError(f"--location: {exc}") from None
        EdgeSettings(
            device="dev",
            emulate=True,
            devices=self.devices,
            rate_hz=self.rate_hz,
            batch=self.batch,
            speedup=self.speedup,
            simulator=SimulatorSettings(location=place),
        )

    @staticmethod
    def add_arguments(parser: argparse.ArgumentParser) -> None:
        """The options of ``magnet up``: these settings' and the compass's drift options."""
        add_options(parser, UpSettings)
        add_drift_arguments(parser)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> UpSettings:
        return from_args(cls, args, drift=drift_from_args(args))

    def drift_arguments(self) -> list[str]:
        """The compass's drift options for these settings."""
        if self.drift is None:
            return ["--no-drift"]
        d = self.drift
        return [
            f"--drift-window={d.window_s:g}",
            f"--drift-windows={d.raise_windows}",
            f"--strength-tol-pct={d.strength_tol_pct:g}",
            f"--dip-tol={d.dip_tol_deg:g}",
            f"--max-age-days={d.max_age_days:g}",
        ]
