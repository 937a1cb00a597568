"""Coverage: how much of the sphere of field directions (or of a level turn) the samples cover, and the attitudes a
person should add, in words.

The sphere is ~100 equal-area cells (a Fibonacci lattice of cell centres; a sample belongs to its nearest centre);
a level turn is 36 ten-degree sectors of heading.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter

import numpy as np

CELL_COUNT = 100
HEADING_SECTORS = 36
#: samples placed in their cells at a time (the rest are not looked at once every cell is hit)
COVERAGE_CHUNK = 1000


def fibonacci_centres(count: int = CELL_COUNT) -> np.ndarray:
    """Centres of ``count`` near-equal-area cells on the unit sphere (Fibonacci lattice), shape (count, 3)."""
    i = np.arange(count) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


_CENTRES = fibonacci_centres()

#: (axis, sign) of the body axis the field points along -> what a person does to get there. The Earth field dips
#: downward in the northern hemisphere (steeply, away from the equator), so "field along body +x" is reached by
#: pointing the nose down; in the southern hemisphere every phrase is flipped (``field_points_down=False``).
_ADVICE: dict[tuple[int, int], str] = {
    (0, 1): "point the nose (x) down",
    (0, -1): "point the nose (x) up",
    (1, 1): "roll right side (y) down",
    (1, -1): "roll left side down",
    (2, 1): "hold it level, top up",
    (2, -1): "turn it upside down",
}
MAX_ADVICE = 3


@dataclasses.dataclass(frozen=True)
class Coverage:
    """How much of the sphere (or of the turn) the samples cover.

    fraction: cells_hit / cell_count in [0, 1]; missing: at most a few phrases, most needed first.
    """

    fraction: float
    cells_hit: int
    cell_count: int
    missing: tuple[str, ...]


def coverage(directions: np.ndarray, *, field_points_down: bool = True) -> Coverage:
    """Coverage of the sphere by field directions (N, 3) (any length; zero rows ignored), body frame.

    Missing cells are named by the dominant body axis of their centre, mapped to an attitude (see ``_ADVICE``),
    grouped and ordered by how many cells each phrase would fill.
    """
    vectors = np.asarray(directions, dtype=float).reshape(-1, 3)
    hit = np.zeros(len(_CENTRES), dtype=bool)
    for start in range(0, len(vectors), COVERAGE_CHUNK):  # a chunk at a time: done once every cell is hit
        chunk = vectors[start : start + COVERAGE_CHUNK]
        # zero and non-finite rows ignored (in the chunk: the rest is not looked at once every cell is hit); the
        # nearest centre is the largest dot product, which no positive scale of a row changes: no need to normalise
        chunk = chunk[np.einsum("ij,ij->i", chunk, chunk) > 0]
        hit[np.argmax(chunk @ _CENTRES.T, axis=1)] = True
        if hit.all():
            break
    empty = _CENTRES[~hit] * (1.0 if field_points_down else -1.0)
    axes = np.argmax(np.abs(empty), axis=1)
    signs = np.sign(empty[np.arange(len(empty)), axes]).astype(int)
    counts = Counter(_ADVICE[(int(a), int(s))] for a, s in zip(axes, signs))
    missing = tuple(phrase for phrase, _ in counts.most_common(MAX_ADVICE))
    return Coverage(float(hit.mean()), int(hit.sum()), len(_CENTRES), missing)


def heading_coverage(field_xy: np.ndarray) -> Coverage:
    """Coverage of a level turn: 36 ten-degree sectors of heading, from the horizontal field (N, 2) or (N, 3).

    The heading of a level device whose horizontal field reads (x, y) is atan2(-y, x) (clockwise from magnetic north);
    missing sectors are merged into ranges ("turn to headings 90-150 deg").
    """
    xy = np.asarray(field_xy, dtype=float)[:, :2]
    heading = np.degrees(np.arctan2(-xy[:, 1], xy[:, 0])) % 360.0
    sector_deg = 360.0 / HEADING_SECTORS
    hit = np.zeros(HEADING_SECTORS, dtype=bool)
    hit[np.unique((heading // sector_deg).astype(int) % HEADING_SECTORS)] = True
    ranges = _empty_ranges(hit, sector_deg)
    missing = tuple(f"turn to headings {lo:.0f}-{hi:.0f} deg" for lo, hi in ranges[:MAX_ADVICE])
    return Coverage(float(hit.mean()), int(hit.sum()), HEADING_SECTORS, missing)


def _empty_ranges(hit: np.ndarray, sector_deg: float) -> list[tuple[float, float]]:
    """Runs of empty sectors (wrapping round 360) as (start_deg, end_deg), longest first."""
    n = len(hit)
    if hit.all():
        return []
    if not hit.any():
        return [(0.0, 360.0)]
    start = int(np.argmax(hit))  # begin scanning at a hit sector so that runs do not straddle the scan start
    runs, run_start = [], None
    for k in range(1, n + 1):
        idx = (start + k) % n
        if not hit[idx] and run_start is None:
            run_start = start + k
        elif hit[idx] and run_start is not None:
            runs.append((run_start, start + k))
            run_start = None
    runs.sort(key=lambda r: r[0] - r[1])
    return [((a % n) * sector_deg, ((b % n) * sector_deg) or 360.0) for a, b in runs]
