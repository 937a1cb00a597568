"""``magnet fit --motor current|throttle``: the motors' field fitted with the calibration, from a recording whose
``current_a`` (A) or ``throttle`` (0..1) column says how hard the motors worked at each sample
(``magnet.calibration.motor_fit``). The record then carries ``motor_ut_per_a`` or ``motor_ut_per_throttle``, and its
quality the figures ``motor_interference_pct`` (compassmot's), ``motor_residual_rms_ut`` and ``motor_fit`` (still or
moving)."""

from __future__ import annotations

import argparse
from collections.abc import Callable

import numpy as np

from magnet.model import Calibration
from magnet.motor import CURRENT, THROTTLE
from services.common.inputs.csvio import SampleTable

COLUMNS = {CURRENT: "current_a", THROTTLE: "throttle"}


def add_motor_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--motor",
        choices=tuple(COLUMNS),
        help="also fit the motors' field against the current_a (A) or throttle (0..1) column (compassmot's model)",
    )


def fit_with_motors(
    table: SampleTable, kind: str, fit_calibration: Callable[[np.ndarray], Calibration], earth_ut: float | None
) -> Calibration:
    """The calibration of ``table.mag`` with its motor model; ValueError naming the missing column."""
    column = COLUMNS[kind]
    if column not in table.columns:
        raise ValueError(f"{table.path}: --motor {kind} needs a {column} column (the samples' {kind}); it has none")
    driver = table.numeric(column)
    from magnet.calibration.motor_fit import fit_with_motor  # only with --motor

    calibration, motor = fit_with_motor(table.mag, driver, kind, fit_calibration, earth_ut)
    quality = calibration.quality.with_extra(
        motor_interference_pct=round(motor.interference_pct, 2),
        motor_residual_rms_ut=round(motor.residual_rms_ut, 4),
        motor_fit=motor.way,
    )
    return calibration.replace(quality=quality)
