"""Figures the dashboard derives from messages: dip, the direction of gravity, covered cells, decimation, the fused
quaternion and the expected field as JSON. Pure numpy, no state.

Units: angles in degrees, fields in uT.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magnet.earth.geomag import EarthField
from magnet.quality import fibonacci_centres

CELL_CENTRES = fibonacci_centres()
HEADING_WINDOW_NS = 60_000_000_000  # the heading plot covers the last 60 s
HEADING_POINTS = 600  # at most this many heading samples go to the page


def acc_direction(pitch_deg: np.ndarray | float, roll_deg: np.ndarray | float) -> np.ndarray:
    """Specific force direction (N, 3) of a still device at pitch and roll (degrees): (sin p, -sin r cos p,
    -cos r cos p), as ``magnet.attitude.heading.pitch_roll_deg`` inverts it."""
    p, r = np.radians(pitch_deg), np.radians(roll_deg)
    return np.stack([np.sin(p), -np.sin(r) * np.cos(p), -np.cos(r) * np.cos(p)], axis=-1)


def dip_deg(bx: float, by: float, bz: float, pitch_deg: float, roll_deg: float) -> float | None:
    """Dip of the field (uT, body frame) below the horizon, degrees, for a device at pitch and roll: asin(B . d / |B|)
    with d the down direction, -``acc_direction`` (``magnet.attitude.heading.dip_angle_deg`` for one sample, without
    numpy's per-call cost: the ingest runs it for every device several times a second). None for a zero field."""
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    down = (-math.sin(p), math.sin(r) * math.cos(p), math.cos(r) * math.cos(p))
    norm = math.sqrt(bx * bx + by * by + bz * bz)
    if norm == 0:
        return None
    return math.degrees(math.asin(max(-1.0, min(1.0, (bx * down[0] + by * down[1] + bz * down[2]) / norm))))


def covered_cells(raw_ut: np.ndarray) -> np.ndarray:
    """Which of the 100 equal-area cells (``magnet.quality``) the raw field directions around the cloud's centre
    ((max + min) / 2 per axis) fall in: bool (100,)."""
    hit = np.zeros(len(CELL_CENTRES), dtype=bool)
    if len(raw_ut) < 2:
        return hit
    centred = raw_ut - (raw_ut.max(axis=0) + raw_ut.min(axis=0)) / 2
    norms = np.linalg.norm(centred, axis=1)
    unit = centred[norms > 0] / norms[norms > 0, None]
    hit[np.unique(np.argmax(unit @ CELL_CENTRES.T, axis=1))] = True
    return hit


def decimate(points: np.ndarray, limit: int) -> list[list[float]]:
    step = max(1, int(np.ceil(len(points) / max(limit, 1))))
    return np.round(points[::step], 2).tolist()


def quat_of(value: Any, index: int) -> tuple[float, ...] | None:
    """The fused attitude quaternion of one sample, when the message carries a usable one (optional field)."""
    if value is None:
        return None
    try:
        quats = np.asarray(value, dtype=float)
        quat = quats[index] if quats.ndim == 2 else quats
    except (TypeError, ValueError, IndexError):
        return None
    return tuple(float(q) for q in quat) if quat.shape == (4,) and np.isfinite(quat).all() else None


def earth_json(earth: EarthField | None) -> dict[str, Any] | None:
    if earth is None:
        return None
    return {
        "total_ut": round(earth.total_ut, 3),
        "inclination_deg": round(earth.inclination_deg, 3),
        "declination_deg": round(earth.declination_deg, 3),
        "horizontal_ut": round(earth.horizontal_ut, 3),
    }


def recent_headings(headings: list[tuple[int, float, float]]) -> list[tuple[int, float, float]]:
    """The (t_ns, magnetic, true) samples of the last ``HEADING_WINDOW_NS`` before the newest, thinned evenly to at
    most ``HEADING_POINTS`` (the newest always kept)."""
    if not headings:
        return []
    since = headings[-1][0] - HEADING_WINDOW_NS
    window = [h for h in headings if h[0] >= since]
    step = max(1, math.ceil(len(window) / HEADING_POINTS))
    return window[::-1][::step][::-1]
