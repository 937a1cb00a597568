"""Turntable calibration of all 12 parameters of u = K T + u0 against a known field (seed 000; docs/design.md).

The sensor sits on a turntable in two mountings and is read at table headings K (deg) in a field of known horizontal
component Bh and vertical component Bv (same unit, e.g. nT). The field in the sensor frame is then (seed 000, eqs.
2 and 5):

    mounting a (x north at K = 0, z up):   T = (Bh cos K,  Bh sin K,  Bv)
    mounting b (x north at K = 0, y down): T = (Bh cos K, -Bv,        Bh sin K)

Closed form from the readings U (mounting a) and U' (mounting b), each a 3-vector of raw codes:

    column 1 of K = (U(0) - U(180)) / (2 Bh)
    column 2 of K = (U(90) - U(270)) / (2 Bh)
    u0            = (U'(0) + U'(180)) / 2 + (column 2 of K) Bv
    column 3 of K = (U(0) + U(180) - 2 u0) / (2 Bv)

Least-squares variant: u_i = K T_i + u0 over every sample of both mountings, solved for the 12 parameters at once
((N, 4) design [T_i, 1] against (N, 3) readings).

The calibration record has matrix = K^-1 and offset = u0, so that T = K^-1 (u - u0) in the unit of Bh and Bv.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import numpy.typing as npt

from magnet.calibration.base import FitError
from magnet.model import Calibration
from magnet.quality import GateThresholds, Geometry, assess, gate

#: table headings (deg) the closed form reads, per mounting
CLOSED_FORM_ANGLES = {"a": (0, 90, 180, 270), "b": (0, 180)}
VARIANTS = ("closed", "lsq")


def field_in_sensor(mounting: str, heading_deg: np.ndarray, horizontal: float, vertical: float) -> np.ndarray:
    """Field T (N, 3) in the sensor frame for a mounting ("a" or "b") and table headings (N,) deg."""
    k = np.radians(np.asarray(heading_deg, dtype=float))
    h_cos, h_sin = horizontal * np.cos(k), horizontal * np.sin(k)
    vert = np.full_like(k, float(vertical))
    layouts = {"a": (h_cos, h_sin, vert), "b": (h_cos, -vert, h_sin)}
    if mounting not in layouts:
        raise FitError(f"unknown mounting {mounting!r}: use 'a' (z up) or 'b' (y down)")
    return np.column_stack(layouts[mounting])


def _reading(readings: Mapping[int, np.ndarray], mounting: str, angle: int) -> np.ndarray:
    if angle not in readings:
        have = ", ".join(str(a) for a in sorted(readings)) or "none"
        raise FitError(
            f"the closed form needs mounting {mounting} at {angle} deg (have: {have}); record that "
            "angle or use the lsq variant"
        )
    value = np.asarray(readings[angle], dtype=float)
    if value.shape != (3,) or not np.all(np.isfinite(value)):
        raise FitError(f"mounting {mounting} at {angle} deg must be 3 finite numbers, got {value!r}")
    return value


def closed_form(
    readings_a: Mapping[int, np.ndarray], readings_b: Mapping[int, np.ndarray], horizontal: float, vertical: float
) -> tuple[np.ndarray, np.ndarray]:
    """(K (3,3), u0 (3,)) from averaged readings per table heading (deg -> (3,) raw) of mountings a and b.

    horizontal, vertical: Bh and Bv, the unit K maps from (K is raw units per field unit).
    """
    if horizontal == 0 or vertical == 0:
        raise FitError("the closed form needs nonzero horizontal and vertical field components")
    a = {angle: _reading(readings_a, "a", angle) for angle in CLOSED_FORM_ANGLES["a"]}
    b = {angle: _reading(readings_b, "b", angle) for angle in CLOSED_FORM_ANGLES["b"]}
    col1 = (a[0] - a[180]) / (2 * horizontal)
    col2 = (a[90] - a[270]) / (2 * horizontal)
    u0 = (b[0] + b[180]) / 2 + col2 * vertical
    col3 = (a[0] + a[180] - 2 * u0) / (2 * vertical)
    return np.column_stack([col1, col2, col3]), u0


def least_squares(mag: np.ndarray, field: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K (3,3), u0 (3,)) minimising sum |u_i - K T_i - u0|^2 for readings mag (N,3) and known fields (N,3)."""
    design = np.column_stack([field, np.ones(len(field))])
    if np.linalg.matrix_rank(design) < 4:
        raise FitError("the known fields do not span 3D plus offset: record both mountings (a and b)")
    sol, *_ = np.linalg.lstsq(design, mag, rcond=None)
    return sol[:3].T, sol[3]


def average_by_angle(mag: np.ndarray, heading_deg: np.ndarray) -> dict[int, np.ndarray]:
    """Mean reading (3,) per table heading rounded to whole degrees modulo 360.

    A reading at 360 deg is kept apart from 0 deg: seed 000 records it to show that the turn closed, and its closed
    form uses the 0 deg readings. It stands in for 0 deg only where no 0 deg reading exists.
    """
    rounded = np.rint(np.asarray(heading_deg, dtype=float)).astype(int)
    angles = np.where(rounded == 360, 360, rounded % 360)
    means = {int(angle): mag[angles == angle].mean(axis=0) for angle in np.unique(angles)}
    if 0 not in means and 360 in means:
        means[0] = means[360]
    return means


def _check_inputs(
    mag: npt.ArrayLike, mounting: npt.ArrayLike, heading_deg: npt.ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    mag = np.asarray(mag, dtype=float)
    mounting = np.asarray(mounting).astype(str)
    heading = np.asarray(heading_deg, dtype=float)
    if mag.ndim != 2 or mag.shape[1] != 3:
        raise FitError(f"samples must be an (N, 3) array of x, y, z readings, got shape {mag.shape}")
    if mounting.shape != (len(mag),) or heading.shape != (len(mag),):
        raise FitError(
            f"mounting and heading_deg need one entry per sample ({len(mag)}), got {mounting.shape} and {heading.shape}"
        )
    if not (np.all(np.isfinite(mag)) and np.all(np.isfinite(heading))):
        raise FitError("samples or headings hold NaN or infinite values: drop those rows before fitting")
    unknown = sorted(set(mounting.tolist()) - {"a", "b"})
    if unknown:
        raise FitError(f"unknown mounting(s) {unknown}: use 'a' (z up) or 'b' (y down)")
    return mag, mounting, heading


def fit_turntable(
    mag: npt.ArrayLike,
    mounting: npt.ArrayLike,
    heading_deg: npt.ArrayLike,
    horizontal: float,
    vertical: float,
    variant: str = "closed",
    *,
    unit: str = "counts",
    field_unit: str = "ut",
    gate_thresholds: GateThresholds | None = None,
) -> Calibration:
    """Calibration from turntable samples: mag (N,3) raw, mounting (N,) "a"/"b", heading_deg (N,) table angle.

    horizontal, vertical: Bh and Bv in ``field_unit`` (the output unit of the record; uT by default, "nt" for the
    seed's gammas). variant "closed" uses the
    per-angle averages at 0/90/180/270 (a) and 0/180 (b); "lsq" uses every sample. The record's quality adds
    ``vector_rms`` (RMS of |A (u - b) - T|, field unit) to the usual figures; the gate ignores coverage (a turntable
    gives two great circles by design).
    """
    if variant not in VARIANTS:
        raise FitError(f"unknown turntable variant {variant!r}: use one of {', '.join(VARIANTS)}")
    mag, mounting, heading = _check_inputs(mag, mounting, heading_deg)
    field = np.empty_like(mag)
    for name in ("a", "b"):
        rows = mounting == name
        field[rows] = field_in_sensor(name, heading[rows], horizontal, vertical)
    if variant == "closed":
        k, u0 = closed_form(
            average_by_angle(mag[mounting == "a"], heading[mounting == "a"]),
            average_by_angle(mag[mounting == "b"], heading[mounting == "b"]),
            horizontal,
            vertical,
        )
    else:
        k, u0 = least_squares(mag, field)
    if np.linalg.cond(k) > 1e8:
        raise FitError("the fitted K is singular: check the field components and the mountings")
    strength = float(np.hypot(horizontal, vertical))
    calibration = Calibration(
        method="turntable" if variant == "closed" else "turntable-lsq",
        offset=u0,
        matrix=np.linalg.inv(k),
        field_strength=strength,
        sample_count=len(mag),
        unit=unit,
        output_unit=field_unit,
    )
    quality = assess(mag, calibration, geometry=Geometry.TURNTABLE)
    vector_rms = float(np.sqrt(np.mean(np.sum((calibration.apply(mag) - field) ** 2, axis=1))))
    quality = quality.with_extra(vector_rms=vector_rms)
    accepted, reason = gate(quality, gate_thresholds)
    return calibration.replace(quality=quality, accepted=accepted, reason=reason)
