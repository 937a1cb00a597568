"""The settings of ``magnet up``, checked in one place before anything starts."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from magnet import wire
from magnet.drift import DEFAULT_DRIFT, DriftSettings
from magnet.place import Location
from services.common.places_options import drift_from_args
from services.common.sim_options import SimulatorSettings
from services.edge.settings import EdgeSettings

MAX_DEVICES = 10_000


@dataclasses.dataclass(frozen=True)
class UpSettings:
    """What ``magnet up`` runs, checked in one place before anything starts: the edge's own checks (rate, batch,
    speedup) through the ``EdgeSettings`` it will run, the location through ``Location.parse``."""

    devices: int = 4
    rate_hz: float = 50.0
    batch: int = 10
    speedup: float = 4.0
    location: str = "50.45,30.52"
    db: Path | None = None
    duration_s: float | None = None
    interval_s: float | None = None
    prefix: str = wire.DEFAULT_PREFIX
    http: str | None = None
    dashboard: bool = True
    drift: DriftSettings | None = DEFAULT_DRIFT  # the compass's drift alerts (None: --no-drift)

    def __post_init__(self) -> None:
        if self.http is not None:
            from services.dashboard.service import parse_http

            parse_http(self.http)
        if not 1 <= self.devices <= MAX_DEVICES:
            raise ValueError(f"--devices must be 1..{MAX_DEVICES}, got {self.devices}")
        if self.duration_s is not None and not self.duration_s >= 0:
            raise ValueError(f"--duration must be >= 0 seconds, got {self.duration_s}")
        if self.interval_s is not None and not self.interval_s > 0:
            raise ValueError(f"--interval must be > 0 seconds, got {self.interval_s}")
        wire.validate_prefix(self.prefix)
        try:
            place = Location.parse(self.location).as_tuple()
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

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> UpSettings:
        return cls(
            devices=int(args.devices),
            rate_hz=float(args.rate),
            batch=int(args.batch),
            speedup=float(args.speedup),
            location=args.location,
            db=args.db,
            duration_s=args.duration,
            interval_s=args.interval,
            prefix=args.prefix,
            http=args.http,
            dashboard=not args.no_dashboard,
            drift=drift_from_args(args),
        )

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
