"""The margin of a held-out comparison (``magnet.quality.motion.margin_deg``): a gain in every run of rows is not
chance, however unevenly the runs gain (a ground robot that turns in a few of them)."""

from __future__ import annotations

import numpy as np

from magnet.quality import motion


def _departures(turning_runs: tuple[int, ...], seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(a fit's departures, no calibration's) deg over 10 runs of 50 rows: the fit's 0.9 deg of noise throughout; the
    raw field's 60 deg where the device turns, 1.5 deg where it stands."""
    rng = np.random.default_rng(seed)
    runs = motion.MARGIN_CHUNKS
    mine = 0.9 * rng.standard_normal(runs * 50)
    theirs = np.concatenate([(60.0 if k in turning_runs else 1.5) * rng.standard_normal(50) for k in range(runs)])
    return mine, theirs


def test_a_gain_in_every_run_is_no_chance_when_the_device_turns_in_two() -> None:
    mine, theirs = _departures((3, 7))
    assert motion._margin(mine, theirs) == 0.0  # before: the raw field's whole figure, which nothing can beat
    reference = float(np.sqrt(np.mean(theirs**2)))
    assert float(np.sqrt(np.mean(mine**2))) < reference  # so the fit passes the comparison


def test_a_run_that_loses_keeps_the_standard_errors() -> None:
    mine, theirs = _departures((3, 7))
    mine[:50] = 3.0 * np.random.default_rng(1).standard_normal(50)  # worse than the still raw field in one run
    margin = motion._margin(mine, theirs)
    assert margin is not None and margin > 0.0
