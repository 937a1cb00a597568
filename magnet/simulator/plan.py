"""The building blocks of the moving trajectories: eased steps (the quintic smoothstep), sums of tones, and endless
plans of segments drawn one after another (with a course and speed plan's closed-form path: ``segment_path``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def smoother(u: np.ndarray) -> np.ndarray:
    """Quintic smoothstep of u clipped to [0, 1]: 0 -> 1 with zero first and second derivatives at both ends."""
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10.0 + u * (-15.0 + 6.0 * u))


def smoother_rate(u: np.ndarray) -> np.ndarray:
    """d smoother / du (zero outside [0, 1])."""
    inside = (u > 0.0) & (u < 1.0)
    return np.where(inside, 30.0 * u**2 * (1.0 - u) ** 2, 0.0)


def plateau(u: np.ndarray, edge: float = 0.25) -> np.ndarray:
    """0 -> 1 over the first ``edge`` of [0, 1], 1, then back to 0 over the last ``edge`` (smooth at every joint)."""
    return smoother(u / edge) * smoother((1.0 - u) / edge)


class Tones:
    """A sum of sinusoids per axis: ``axes`` x ``count`` tones, frequencies uniform in ``hz``, random phases,
    ``amplitude`` (per axis or one number) per tone. ``__call__(t)`` -> (N, axes)."""

    def __init__(
        self, rng: np.random.Generator, axes: int, count: int, hz: tuple[float, float], amplitude: Any
    ) -> None:
        self.hz = rng.uniform(hz[0], hz[1], (axes, count))
        self.phase = rng.uniform(0.0, 2.0 * np.pi, (axes, count))
        self.amplitude = np.broadcast_to(np.asarray(amplitude, dtype=float), (axes,))[:, None]

    def __call__(self, t: np.ndarray) -> np.ndarray:
        angle = 2.0 * np.pi * self.hz[None] * np.asarray(t, dtype=float)[:, None, None] + self.phase[None]
        return np.sum(self.amplitude[None] * np.sin(angle), axis=-1)


class Segments:
    """An endless plan of manoeuvres drawn one after another: ``draw(rng, state) -> (duration_s, row)`` where ``row``
    is a dict of numbers and ``state`` the previous row (None first). Extended lazily as later times are asked for,
    so the plan is the same whether it is evaluated at once or block by block."""

    def __init__(
        self,
        rng: np.random.Generator,
        draw: Callable[[np.random.Generator, dict[str, Any] | None], tuple[float, dict[str, Any]]],
    ) -> None:
        self.rng, self.draw = rng, draw
        self.starts: list[float] = [0.0]
        self.durations: list[float] = []
        self.rows: list[dict[str, Any]] = []

    def locate(self, t: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        """For times t (N,) (negative times are the start): (each row field at its segment (N,), u in [0, 1] within
        the segment (N,), segment duration (N,))."""
        t = np.maximum(np.asarray(t, dtype=float), 0.0)
        latest = float(t.max()) if t.size else 0.0
        while self.starts[-1] <= latest:
            duration, row = self.draw(self.rng, self.rows[-1] if self.rows else None)
            self.durations.append(float(duration))
            self.rows.append(row)
            self.starts.append(self.starts[-1] + float(duration))
        k = np.searchsorted(np.asarray(self.starts), t, side="right") - 1
        durations = np.asarray(self.durations)[k]
        u = (t - np.asarray(self.starts)[k]) / durations
        fields = {name: np.array([row[name] for row in self.rows])[k] for name in self.rows[0]}
        return fields, u, durations


def smoother_integral(u: np.ndarray) -> np.ndarray:
    """Integral of ``smoother`` from 0 to u (u clipped to [0, 1]): u^4 (2.5 - 3 u + u^2); 1/2 over [0, 1]."""
    u = np.clip(u, 0.0, 1.0)
    return u**4 * (2.5 + u * (-3.0 + u))


def segment_path(plan: Segments, distance_starts: list[float], t: np.ndarray) -> dict[str, np.ndarray]:
    """A course and speed plan (rows with yaw0, dyaw deg magnetic; v0, dv m/s; each eased by ``smoother``) at times
    t (N,): course_deg, speed_ms, along_ms2 (dspeed/dt), lateral_ms2 (speed x course rate, + to the right),
    turn_rads (course rate, rad/s), distance_m along the path from the start (closed form). ``distance_starts``
    (the distance at each segment's start, [0.0] at first) is the caller's and grows with the plan."""
    row, u, duration = plan.locate(t)
    started = t > 0.0
    turn = np.where(started, np.radians(row["dyaw"]) * smoother_rate(u) / duration, 0.0)
    speed = row["v0"] + row["dv"] * smoother(u)
    while len(distance_starts) < len(plan.rows):
        k = len(distance_starts) - 1
        row_k = plan.rows[k]
        distance_starts.append(distance_starts[-1] + plan.durations[k] * (row_k["v0"] + 0.5 * row_k["dv"]))
    segment = np.searchsorted(np.asarray(plan.starts), np.maximum(t, 0.0), side="right") - 1
    covered = duration * (row["v0"] * np.clip(u, 0.0, 1.0) + row["dv"] * smoother_integral(u))
    return {
        "course_deg": row["yaw0"] + row["dyaw"] * smoother(u),
        "speed_ms": speed,
        "along_ms2": np.where(started, row["dv"] * smoother_rate(u) / duration, 0.0),
        "lateral_ms2": speed * turn,
        "turn_rads": turn,
        "distance_m": np.asarray(distance_starts)[segment] + covered,
    }


def random_sign(rng: np.random.Generator) -> float:
    """-1 or +1, evenly."""
    return float(rng.choice([-1.0, 1.0]))
