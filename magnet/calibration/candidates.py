"""The candidates a field fit chooses between, and the choice: every rung the motion identifies, and a plain sphere
with its radius free, each judged by what it does to heading on held-out samples (docs/field-calibration.md).

Why more than the richest identified rung: the rungs hold |B| to the World Magnetic Model's and the vertical field
to its dip, which pins an offset along the vertical that a device kept near one attitude cannot show. When the
sensor's own gains are a few % off (a phone's soft iron), those priors bend the horizontal fit to make up for them:
on fieldsim's walk-phoning (seed 2026, 100 Hz) the planar rung left 3.4 deg of causal heading RMS and the offset
rung 2.4, where a sphere with its radius free, whose far-off vertical offset bends no heading at that attitude, left
1.5 (the true calibration: 1.6). The held-out heading consistency ranks them as heading does (3.3, 2.6, 2.4, truth
2.3 deg); coverage alone cannot. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from magnet.calibration.base import FitError
from magnet.calibration.ladder import IDENTIFIED_DEG, RungFit, first_offset, fit_rung
from magnet.calibration.rungs import (
    ISO,
    LADDER,
    LEVEL_OFFSET,
    OFFSET,
    PLANAR_LADDER,
    Evidence,
    Rung,
    is_planar,
    mean_down,
)
from magnet.model import Calibration

#: another candidate replaces the richest identified rung only when its held-out heading consistency is lower by more
#: than this fraction: the figure is noisy (on a simulated tilted turn, 1.80 deg for the offset rung against 1.94 for
#: the planar one, whose heading was the better), and the richer model is the one the motion was shown to identify
SWITCH_GAIN = 0.10
#: with a gyroscope, another candidate replaces the richest identified rung when the RMS of its field's turn against
#: the gyroscope's (``magnet.calibration.turning``, quality ``turn_residual_ut``) is lower by more than this fraction:
#: the residual is mostly the sensor's noise (0.7 uT for a phone's 0.5), an offset a few uT off adds a few %
TURN_GAIN = 0.05
#: the plain sphere: the offset and an isotropic scale, by least squares with the radius free (its record is an
#: "offset" record: the matrix kept up to its scale)
SPHERE = Rung("offset", (ISO,), ("offset", "scale (the radius free)"), ("matrix (up to its scale)",))


def sphere_fit(ev: Evidence, rows: np.ndarray | None = None) -> RungFit:
    """The sphere |A0 (m - o)| = R through the rows (N,) bool (None: all) by algebraic least squares, A0 the kept
    matrix; the record's matrix is A0 F / R (F the expected |B|). FitError when the samples give no sphere."""
    used = np.ones(len(ev.mag), dtype=bool) if rows is None else rows
    u = ev.mag[used] @ ev.matrix0.T
    design = np.hstack([2.0 * u, np.ones((len(u), 1))])
    solution, *_ = np.linalg.lstsq(design, np.einsum("ij,ij->i", u, u), rcond=None)
    centre = solution[:3]
    radius_sq = float(solution[3] + centre @ centre)
    if not (np.all(np.isfinite(solution)) and radius_sq > 0):
        raise FitError("the samples give no sphere: keep the device turning")
    scale = ev.field_ut / math.sqrt(radius_sq)
    if ev.vertical_ut is not None and ev.down is not None and is_planar(ev.down):
        centre, scale = _pinned(u, ev.down[used], centre, ev.field_ut, ev.vertical_ut, scale)
    offset = np.linalg.solve(ev.matrix0, centre)
    matrix = ev.matrix0 * scale
    b = (ev.mag[used] - offset) @ matrix.T
    vertical = math.nan
    if ev.down is not None:
        down = ev.down[used]
        known = np.all(np.isfinite(down), axis=1)
        if known.any():
            vertical = float(np.mean(np.einsum("ni,ni->n", down[known], b[known])))
    spread = float(np.sqrt(np.mean((np.linalg.norm(b, axis=1) - ev.field_ut) ** 2)))
    return RungFit(SPHERE, offset, matrix, vertical, math.nan, (), {"magnitude": spread}, int(used.sum()))


def _pinned(
    u: np.ndarray, down: np.ndarray, centre: np.ndarray, field_ut: float, vertical_ut: float, scale: float
) -> tuple[np.ndarray, float]:
    """(centre (3,), scale) moved along the mean down so that the field's mean |B| is field_ut and its mean vertical
    vertical_ut (the WMM's), the centre's horizontal part kept: a device kept near one attitude shows its horizontal
    centre, not its vertical one, which the sphere leaves wherever its radius put it (a car: 40 uT off, every dip
    then 'disturbed'). u (N, 3) the samples in the kept matrix's frame, down (N, 3) body down (NaN rows unknown);
    the sphere's own (centre, scale) when no move along the vertical gives both."""
    known = np.all(np.isfinite(down), axis=1)
    if known.sum() < 30:
        return centre, scale
    u, d = u[known], down[known]
    n = mean_down(d)
    ratio = vertical_ut / field_ut  # sin(dip) the WMM expects

    def excess(t: float) -> float:  # mean vertical over mean |B| at the centre moved by t along n, less sin(dip)
        r = u - centre - t * n
        return float(np.mean(np.einsum("ij,ij->i", d, r)) / np.mean(np.linalg.norm(r, axis=1))) - ratio

    lo, hi = -4.0 * field_ut, 4.0 * field_ut
    at_lo = excess(lo)
    if at_lo * excess(hi) > 0:
        return centre, scale
    for _ in range(60):  # bisection: the vertical share falls as the centre moves down (excess at lo kept)
        mid = 0.5 * (lo + hi)
        at_mid = excess(mid)
        lo, hi, at_lo = (mid, hi, at_mid) if at_mid * at_lo > 0 else (lo, mid, at_lo)
    moved = centre + 0.5 * (lo + hi) * n
    return moved, field_ut / float(np.mean(np.linalg.norm(u - moved, axis=1)))


def identified(ev: Evidence, planar: bool) -> tuple[list[RungFit], dict[str, float]]:
    """(every rung the motion identifies, richest first; every tried rung's ``identified_deg``); FitError when even
    the offset is not identified (the ladder's identifiability rule, ``IDENTIFIED_DEG``)."""
    start = first_offset(ev)
    tried: dict[str, float] = {}
    found = []
    base = fit_rung(ev, LEVEL_OFFSET if planar else OFFSET, start)
    for rung in PLANAR_LADDER if planar else LADDER:
        try:
            result = base if rung is base.rung else fit_rung(ev, rung, base.offset)
        except (FitError, np.linalg.LinAlgError):
            continue
        tried[rung.name] = result.identified_deg
        if result.identified_deg <= IDENTIFIED_DEG:
            found.append(result)
    if not found:
        figures = ", ".join(f"{name} {value:.2g} deg" for name, value in tried.items())
        raise FitError(
            f"the motion does not identify even the offset (heading error its noise leaves: {figures}, limit "
            f"{IDENTIFIED_DEG:g} deg): turn the device through more headings and tilts"
        )
    return found, tried


def refit(ev: Evidence, result: RungFit, rows: np.ndarray) -> RungFit:
    """The candidate ``result`` fitted again on the rows (N,) bool only (its held-out fit)."""
    if result.rung is SPHERE:
        return sphere_fit(ev, rows)
    return fit_rung(ev, result.rung, result.offset, rows)


def _figure(record: Calibration, key: str) -> float:
    """The record's quality figure ``key``; inf where it has none."""
    value = record.quality.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        return math.inf
    return float(value)


def _turn(record: Calibration) -> float:
    return _figure(record, "turn_residual_ut")


def _consistency(record: Calibration) -> float:
    return _figure(record, "holdout_heading_consistency_deg")


def best(records: Sequence[tuple[RungFit, Calibration]]) -> Calibration:
    """The first accepted record (the richest rung), unless another's held-out heading consistency is lower by more
    than SWITCH_GAIN of its own (then the lowest), its quality listing every candidate (``candidates``: model, fit,
    held-out heading consistency, accepted); the first
    record (refused) when none was accepted."""
    listed = [
        {
            "model": result.rung.name,
            "fit": "sphere" if result.rung is SPHERE else "ladder",
            "holdout_heading_consistency_deg": None if math.isinf(_consistency(record)) else _consistency(record),
            "turn_residual_ut": None if math.isinf(_turn(record)) else _turn(record),
            "accepted": record.accepted,
        }
        for result, record in records
    ]
    accepted = [record for _, record in records if record.accepted]
    chosen = accepted[0] if accepted else records[0][1]
    turned = len(accepted) >= 2 and all(math.isfinite(_turn(record)) for record in accepted)
    if turned:  # the field's turn against the gyroscope's, which no tilt filter bends
        better = min(accepted, key=_turn)
        if _turn(better) < (1.0 - TURN_GAIN) * _turn(chosen):
            chosen = better
    else:
        better = min(accepted, key=_consistency) if accepted else chosen
        if _consistency(better) < (1.0 - SWITCH_GAIN) * _consistency(chosen):
            chosen = better
    quality = chosen.quality.with_extra(candidates=listed)
    if len(accepted) < 2:
        return chosen.replace(quality=quality)
    by = "the field's turn against the gyroscope's" if turned else "held-out heading consistency"
    why = f"chosen by {by} among {len(accepted)} accepted candidates"
    return chosen.replace(quality=quality, reason=f"{chosen.reason}; {why}")
