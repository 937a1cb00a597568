"""Whether a held-out gain is more than chance (``magnet.quality.motion``; docs/field-calibration.md, "Judged by
heading"). Both take the held-out departures (M,) deg of the candidate's field ("mine") and of the reference's
("theirs") on the same rows, and give the margin (deg) by which mine's RMS must be under theirs.

- ``difference_margin``, against a calibration in force: both fields' departures are near the noise floor outside
  what bends them, and the mean of the differences of squares over ``CHUNKS`` runs of consecutive rows
  (neighbouring samples are not independent) gives its uncertainty (two standard errors).
- ``ratio_margin``, against the raw field: a raw field's departures grow with the turn (the hard iron turns with the
  device, the Earth's field does not), and so do those of a field with an offset error, so their **ratio** is what
  stays alike from one turn to the next, while their difference is the turn's size; and a stretch in which the
  device did not turn holds no evidence at all (every field is constant there, up to its noise). So the rows are cut
  into ``CHUNKS`` runs of equal shares of the device's rotation, the log of the ratio of the RMS departures taken in
  each, and two standard errors of their mean is the uncertainty of the whole figure's log ratio. Runs of one turn
  are not independent of each other, so the gain must also hold on ``MIN_TURNS`` separate stretches (the
  ``STRETCH_S`` stretches the departures are measured in) in which the device turned by at least ``MIN_TURN_DEG``:
  over a smaller turn a candidate whose offset bends heading by 3 deg (its field 2 % of |B| off at 67 deg of dip)
  departs by less than the noise (0.02 rad * 0.5 rad = 0.6 deg), so its departures say nothing for it.
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
    """``ratio_margin`` with how the device turned (a comparison with the raw field), else ``difference_margin``."""
    return difference_margin(mine, theirs) if turned is None else ratio_margin(mine, theirs, turned)


def difference_margin(mine: np.ndarray | None, theirs: np.ndarray | None) -> float | None:
    """The margin from the differences of squares over runs of consecutive rows; None with too few rows."""
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
