"""The margin of a held-out comparison: how much more constant a field must be than another's before the difference
is more than chance (``magnet.quality.motion``)."""

from __future__ import annotations

import math

import numpy as np

#: runs of consecutive held-out samples whose spread gives the uncertainty of a comparison
MARGIN_CHUNKS = 10
#: a comparison's gains are also tested in degrees, run by run, where the reference's held-out figure is at least
#: this many times the candidate's: a raw field against a fit made from turns that show its hard iron
GAIN_RATIO = 4.0


def departures_margin(mine: np.ndarray | None, theirs: np.ndarray | None) -> float | None:
    """How much better than ``theirs`` (deg) ``mine`` must be for the difference to be more than chance: mine and theirs
    (N,) the departures (deg) of two fields from constant on the same rows (``magnet.quality.motion.margin_deg``);
    None when there are too few rows.

    Two tests, the smaller margin kept. The squared departures' chunk means (two standard errors of their mean,
    turned into degrees below ``theirs``'s figure). And, where ``theirs`` is at least ``GAIN_RATIO`` times
    ``mine`` (a raw field against a first fit, not two fits against each other), the gains in degrees, chunk by
    chunk: a vehicle's raw field departs from constant only in its turns (its hard iron turning with it), 13-50 deg
    there and under 1 deg on the straights, and the squares' chunk means then spread so widely that two standard
    errors of them exceeded the raw field's whole figure even where every chunk was 5-50 times better (a robot's fit
    at 0.9 deg against 21 deg). That margin is two standard errors of the chunks' mean gain, plus whatever the whole
    rows' gain exceeds that mean by (both must exceed two standard errors)."""
    if mine is None or theirs is None or len(mine) < 4 * MARGIN_CHUNKS:
        return None
    chunks = np.array([c.mean() for c in np.array_split(theirs**2 - mine**2, MARGIN_CHUNKS)])
    uncertainty = 2.0 * float(chunks.std(ddof=1)) / math.sqrt(MARGIN_CHUNKS)
    reference = float(np.mean(theirs**2))
    squared = math.sqrt(reference) - math.sqrt(max(reference - uncertainty, 0.0))
    held = math.sqrt(float(np.mean(mine**2)))
    if math.sqrt(reference) < GAIN_RATIO * held:
        return squared
    theirs_rms = np.array([math.sqrt(c.mean()) for c in np.array_split(theirs**2, MARGIN_CHUNKS)])
    mine_rms = np.array([math.sqrt(c.mean()) for c in np.array_split(mine**2, MARGIN_CHUNKS)])
    gains = theirs_rms - mine_rms
    gain_uncertainty = 2.0 * float(gains.std(ddof=1)) / math.sqrt(MARGIN_CHUNKS)
    in_degrees = gain_uncertainty + max(0.0, math.sqrt(reference) - held - float(gains.mean()))
    return min(squared, in_degrees)
