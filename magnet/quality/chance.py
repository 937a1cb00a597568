"""Whether a held-out gain is more than chance (``magnet.quality.motion``; docs/field-calibration.md, "Judged by
heading"). Each takes the held-out departures (M,) deg of the candidate's field ("mine") and of the reference's
("theirs") on the same rows, and gives the margin (deg) by which mine's RMS must be under theirs.

- ``difference_margin``, the test of every comparison: the mean of the differences of squares over ``CHUNKS`` runs
  of consecutive rows (neighbouring samples are not independent) gives its uncertainty (two standard errors).
- ``ratio_margin``, against the raw field only where that test has no power at all (``margin``). A raw field's
  departures grow with the turn (the hard iron turns with the device, the Earth's field does not), so a device that
  turned in two of the ten runs of time (a robot or a boat between long straights) has two runs of squares
  hundreds of times the rest, their spread is larger than the raw field's whole mean square, and the difference
  test refuses even a fit whose field does not depart at all: it measures when the device turned, not whether
  the fit helps. Then the rows are cut into ``CHUNKS`` runs of equal shares of the device's rotation instead (a
  stretch in which the device did not turn holds no evidence: every field is constant there, up to its noise), the
  log of the ratio of the RMS departures is taken in each (the ratio stays alike from one turn to the next, the
  difference is the turn's size), and two standard errors of their mean is the uncertainty of the whole figure's
  log ratio. Runs of one turn are not independent of each other (the held-out rows interleave with the fitted
  ones), so the gain must also hold on ``MIN_TURNS`` separate stretches (the ``STRETCH_S`` stretches the departures
  are measured in) in which the device turned by at least ``MIN_TURN_DEG``: over a smaller turn a candidate whose
  offset bends heading by 3 deg departs by less than the noise, so its departures say nothing for it.

Where the difference test has any power (a tumble, a walk in a pocket or a swinging hand, whose sway turns the phone
in every run) it decides alone, as before; the ratio test only stands in where nothing could pass, and only for a
level vehicle (``vehicle``: no walker's steps) in an undisturbed field. A phone held level by a walker (texting,
phoning) turns at corners as a robot does, but the first records the ratio test let it take earlier were measured
worse (tuning seeds: phoning 0.87 -> 1.29 deg, texting past doors 1.78 -> 2.52; docs/field-calibration.md), and a
door's edge the flags missed bends a fit that still beats the raw field's hard iron tenfold: the walks and a
collection that saw a disturbed field keep the difference test alone.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

#: runs of held-out rows whose spread gives the uncertainty of a comparison
CHUNKS = 10
#: the least turn (deg, the widest angle from the stretch's first attitude) of a stretch that vouches for a fit
MIN_TURN_DEG = 30.0
#: separate stretches so turned on which a fit must beat the raw field by the comparison's margin
MIN_TURNS = 2
#: a walker's steps: the specific force's magnitude varies by more than this fraction of its median (one standard
#: deviation, over STEP_WINDOW_S, in the median window): the compass's gait detection asks 1 m/s^2
#: (``TurnSettings.gait_sd_ms2``); the simulator's walks vary by 2.5-3 m/s^2, its car, boat and robot by 0.05-0.5
STEP_SD_FRACTION = 0.1
#: the window (s) over which the steps' variation is taken (``TurnSettings.gait_s``)
STEP_WINDOW_S = 2.0


def vehicle(acc: np.ndarray | None, period_s: float | None) -> bool:
    """Whether specific forces acc (N, 3) (any unit) every ``period_s`` s show no walker's steps: in the median window
    of ``STEP_WINDOW_S`` their magnitude's standard deviation is within ``STEP_SD_FRACTION`` of its median. False
    without an accelerometer, a period, or a whole window."""
    if acc is None or period_s is None or period_s <= 0:
        return False
    norm = np.linalg.norm(np.asarray(acc, dtype=float), axis=1)
    width = max(2, round(STEP_WINDOW_S / period_s))
    count = len(norm) // width
    if count == 0:
        return False
    windows = norm[: count * width].reshape(count, width)
    return bool(np.median(windows.std(axis=1)) <= STEP_SD_FRACTION * np.median(norm))


@dataclasses.dataclass(frozen=True)
class Turns:
    """How the device turned over the held-out rows (M of them): share (M,) the rotation (rad) summed from the first
    held-out row (a row's turn from the row before counted when both are held out), stretch (M,) int each row's
    stretch, -1 where that stretch turned by less than ``MIN_TURN_DEG``."""

    share: np.ndarray
    stretch: np.ndarray


def turns(attitude: np.ndarray | None, rows: np.ndarray, period_s: float | None, stretch_s: float) -> Turns | None:
    """``Turns`` of the held-out rows (N,) bool, from the attitude (N, 4) body -> earth of every row, rows
    ``period_s`` apart, in stretches of ``stretch_s``; None without an attitude or a period."""
    if attitude is None or period_s is None or not rows.any():
        return None
    q = np.asarray(attitude, dtype=float)
    step = np.zeros(len(q))
    step[1:] = 2.0 * np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", q[1:], q[:-1])), 0.0, 1.0))
    step[1:][~rows[:-1]] = 0.0
    label = (np.arange(len(q)) * period_s // stretch_s).astype(int)
    starts = np.flatnonzero(np.diff(label, prepend=-1))
    first = np.repeat(starts, np.diff(np.append(starts, len(q))))
    angle = np.degrees(2.0 * np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", q, q[first])), 0.0, 1.0)))
    widest = np.zeros(label[-1] + 1 if len(label) else 0)
    np.maximum.at(widest, label, angle)
    held = label[rows]
    return Turns(np.cumsum(step[rows]), np.where(widest[held] >= MIN_TURN_DEG, held, -1))


def _rms(values: np.ndarray) -> float:
    return math.sqrt(float(np.mean(values**2)))


def margin(mine: np.ndarray | None, theirs: np.ndarray | None, turned: Turns | None = None) -> float | None:
    """``difference_margin``; with how the device turned (a comparison with the raw field), ``ratio_margin``
    where the difference margin is the reference's whole figure (no fit could pass it). None with too few rows."""
    by_difference = difference_margin(mine, theirs)
    if by_difference is None or turned is None or mine is None or theirs is None:  # the caller's "a vehicle"
        return by_difference
    if by_difference < _rms(theirs) * (1.0 - 1e-9):
        return by_difference
    by_ratio = ratio_margin(mine, theirs, turned)
    return by_difference if by_ratio is None else min(by_difference, by_ratio)


def difference_margin(mine: np.ndarray | None, theirs: np.ndarray | None) -> float | None:
    """The margin from the differences of squares over runs of consecutive rows, turned into degrees below
    theirs's RMS; None with too few rows."""
    if mine is None or theirs is None or len(mine) < 4 * CHUNKS:
        return None
    chunks = np.array([c.mean() for c in np.array_split(theirs**2 - mine**2, CHUNKS)])
    uncertainty = 2.0 * float(chunks.std(ddof=1)) / math.sqrt(CHUNKS)
    reference = float(np.mean(theirs**2))
    return math.sqrt(reference) - math.sqrt(max(reference - uncertainty, 0.0))


def ratio_margin(mine: np.ndarray | None, theirs: np.ndarray | None, turned: Turns) -> float | None:
    """The margin from the log ratios over runs of equal rotation, the whole figure of theirs (nothing passes)
    unless the gain holds on ``MIN_TURNS`` stretches that turned; None with too few rows."""
    if mine is None or theirs is None or len(mine) < 4 * CHUNKS:
        return None
    reference = _rms(theirs)
    if turned.share[-1] <= 0.0:
        return reference
    labels = np.minimum((turned.share * CHUNKS / turned.share[-1]).astype(int), CHUNKS - 1)
    cuts = np.flatnonzero(np.diff(labels)) + 1
    pairs = zip(np.split(mine, cuts), np.split(theirs, cuts), strict=True)
    logs = np.array([math.log(max(_rms(t), 1e-9) / max(_rms(m), 1e-9)) for m, t in pairs])
    uncertainty = 2.0 * float(logs.std(ddof=1)) / math.sqrt(len(logs)) if len(logs) > 1 else math.inf
    need = math.exp(uncertainty)
    held = sum(
        _rms(theirs[turned.stretch == s]) > need * _rms(mine[turned.stretch == s])
        for s in np.unique(turned.stretch[turned.stretch >= 0])
    )
    return reference * (1.0 - 1.0 / need) if held >= MIN_TURNS else reference
