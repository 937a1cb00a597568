"""The field ladder's model: its rungs (which parameters each frees), the evidence a fit sees, and the basis of E in
B = (I + E) A0 (m - o) (``magnet.calibration.ladder`` fits them; docs/field-calibration.md). Pure numpy."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from magnet.calibration.gyro_ellipsoid import gyro_attitudes, kept_windows, windows
from magnet.frames import rotation_vector_to_matrix

#: a device whose down stays within this of its z axis in PLANAR_FRACTION of the samples is planar (deg)
PLANAR_TILT_DEG = 20.0
PLANAR_FRACTION = 0.95
#: what a planar record says
PLANAR_NOTE = f"planar: within {PLANAR_TILT_DEG:g} deg of level"
#: at most this many gyroscope windows (spread evenly)
MAX_WINDOWS = 2000

#: E's symmetric basis: (row, column) of each parameter; the last, ``ISO``, is the identity (an isotropic scale,
#: which heading does not see: the offset rung frees it so that a sensor's gain error does not bend the offset)
_E_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
ISO = 6
#: then three for the plane square to the device's mean vertical (``Evidence.axis``): p p^T, q q^T, p q^T + q p^T
LEVEL = (7, 8, 9)


@dataclasses.dataclass(frozen=True)
class Rung:
    """A model of the ladder: its name (the record's method), the E parameters it frees (indices into
    ``_E_INDEX``), and what it estimates and keeps, in words."""

    name: str
    e_free: tuple[int, ...]
    estimated: tuple[str, ...]
    kept: tuple[str, ...]


OFFSET = Rung("offset", (ISO,), ("offset",), ("matrix (up to its scale)",))
#: a level device cannot tell its gain from its vertical offset: its offset rung keeps the matrix whole
LEVEL_OFFSET = Rung("offset", (), ("offset",), ("matrix",))
SCALE = Rung("offset+scale", (0, 1, 2), ("offset", "per-axis scale"), ("cross-axis terms",))
PLANAR = Rung("planar", LEVEL, ("offset", "horizontal soft iron"), ("vertical scale and cross-axis terms",))
FULL = Rung("ellipsoid", (0, 1, 2, 3, 4, 5), ("offset", "soft iron"), ())
#: the rungs tried from the richest down, for a device that tilts and for one kept level
LADDER: tuple[Rung, ...] = (FULL, SCALE, OFFSET)
PLANAR_LADDER: tuple[Rung, ...] = (PLANAR, LEVEL_OFFSET)
RUNGS: dict[str, Rung] = {r.name: r for r in (OFFSET, SCALE, PLANAR, FULL)}


@dataclasses.dataclass(frozen=True)
class Evidence:
    """What the fit sees: mag (N, 3) raw; down (N, 3) unit down in body axes (NaN rows unknown) or None; the
    gyroscope's windows as (starts (M,), ends (M,), P^T (M, 3, 3)) or None; period_s (s) or None; field_ut F;
    vertical_ut the WMM's F sin(dip) or None (then free); matrix0 (3, 3) and offset0 (3,) the kept calibration."""

    mag: np.ndarray
    down: np.ndarray | None
    spans: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    period_s: float | None
    field_ut: float
    vertical_ut: float | None
    matrix0: np.ndarray
    offset0: np.ndarray

    @functools.cached_property
    def basis(self) -> np.ndarray:
        """E's basis (``basis``) with the plane square to the mean down direction."""
        return basis(mean_down(self.down))

    def only(self, rows: np.ndarray) -> tuple[Evidence, np.ndarray]:
        """(this evidence on the rows (N,) bool and the ends of the windows whose both ends are among them, the
        rows' mask in it): the fit then works on those samples alone."""
        keep = rows.copy()
        spans = None
        if self.spans is not None:
            starts, ends, back = self.spans
            ok = rows[starts] & rows[ends]
            spans = (starts[ok], ends[ok], back[ok])
        index = np.flatnonzero(keep)
        position = np.full(len(rows), -1)
        position[index] = np.arange(len(index))
        if spans is not None:
            spans = (position[spans[0]], position[spans[1]], spans[2])
        down = None if self.down is None else self.down[index]
        smaller = dataclasses.replace(self, mag=self.mag[index], down=down, spans=spans)
        smaller.__dict__["basis"] = self.basis  # the whole recording's plane
        return smaller, np.ones(len(index), dtype=bool)

    @property
    def horizontal_ut(self) -> float:
        vertical = self.vertical_ut if self.vertical_ut is not None else 0.6 * self.field_ut
        return max(math.sqrt(max(self.field_ut**2 - vertical**2, 0.0)), 0.1 * self.field_ut)


def gyro_spans(
    gyr_rads: np.ndarray, period_s: float, keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The gyroscope's windows (``gyro_ellipsoid.windows``, at most MAX_WINDOWS) with P^T of each, both ends in
    ``keep`` (None: all); None when there are fewer than 12."""
    gyr = np.asarray(gyr_rads, dtype=float)
    starts, ends = kept_windows(*windows(gyr, period_s), keep, MAX_WINDOWS)
    if len(starts) < 12:
        return None
    turned = gyro_attitudes(rotation_vector_to_matrix(gyr * period_s))
    back = np.transpose(turned[ends], (0, 2, 1)) @ turned[starts]
    return starts, ends, back


def mean_down(down: np.ndarray | None) -> np.ndarray:
    """The unit mean of the known down directions (N, 3) in body axes; body z when none is known."""
    if down is None:
        return np.array([0.0, 0.0, 1.0])
    known = down[np.all(np.isfinite(down), axis=1)]
    total = known.sum(axis=0) if len(known) else np.zeros(3)
    norm = float(np.linalg.norm(total))
    return total / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


def is_planar(down: np.ndarray | None) -> bool:
    """Whether the known down directions (N, 3) stay within PLANAR_TILT_DEG of their mean (``mean_down``) in
    PLANAR_FRACTION of the rows: a vehicle that only yaws, or a phone held the same way while its holder turns."""
    if down is None:
        return False
    known = down[np.all(np.isfinite(down), axis=1)]
    if len(known) < 30:
        return False
    cosine = known @ mean_down(known) / np.linalg.norm(known, axis=1)
    return float(np.mean(cosine >= math.cos(math.radians(PLANAR_TILT_DEG)))) >= PLANAR_FRACTION


def basis(axis: np.ndarray) -> np.ndarray:
    """E's basis (10, 3, 3): the six symmetric ones of ``_E_INDEX``, the identity (ISO), and the three of the plane
    square to ``axis`` (3,) unit (LEVEL)."""
    out = np.zeros((10, 3, 3))
    for k, (i, j) in enumerate(_E_INDEX):
        out[k, i, j] = out[k, j, i] = 1.0
    out[ISO] = np.eye(3)
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    p = np.cross(axis, helper)
    p /= np.linalg.norm(p)
    q = np.cross(axis, p)
    out[LEVEL[0]], out[LEVEL[1]] = np.outer(p, p), np.outer(q, q)
    out[LEVEL[2]] = np.outer(p, q) + np.outer(q, p)
    return out


def matrix_of(ev: Evidence, e: np.ndarray) -> np.ndarray:
    return (np.eye(3) + np.einsum("k,kij->ij", e, ev.basis)) @ ev.matrix0
