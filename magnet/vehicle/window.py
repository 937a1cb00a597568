"""The recent samples of each vehicle's compasses, for ``magnet.vehicle.consistency``: per device its times (s), the
field to compare (uT, body frame), battery current (A) and throttle (0..1) (NaN where unknown), at most one sample per
``STEP_S`` and the last ``WINDOW_S`` of them; at most ``max_vehicles`` vehicles (the least recently seen forgotten
first). Pure: the compass feeds it from each step."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from magnet.bounded import Recent
from magnet.vehicle.membership import vehicle_of

if TYPE_CHECKING:
    from magnet.vehicle.consistency import Series

#: the span compared (s): a minute of flight and a half
WINDOW_S = 90.0
#: one sample kept per this long (s): 10 Hz follows a vehicle's turns and its throttle
STEP_S = 0.1
#: rows kept per device (WINDOW_S / STEP_S)
MAX_ROWS = int(WINDOW_S / STEP_S)
DEFAULT_MAX_VEHICLES = 1000


class VehicleWindows:
    """Rows (n, 6) per device of each vehicle: t_s, field_ut (3), current_a, throttle."""

    def __init__(self, max_vehicles: int = DEFAULT_MAX_VEHICLES) -> None:
        self.vehicles: Recent[str, dict[str, np.ndarray]] = Recent(max_vehicles)

    def observe(
        self,
        devices: Sequence[str],
        bounds: Sequence[int],
        t_ns: np.ndarray,
        mag_ut: np.ndarray,
        current_a: np.ndarray,
        throttle: np.ndarray,
        correction: Callable[[int], tuple[np.ndarray, np.ndarray] | None],
        vehicles: Sequence[str] | None = None,
    ) -> None:
        """One step's samples: batch b (of ``devices``) is samples bounds[b] .. bounds[b+1]; t_ns (S,), mag_ut
        (S, 3) uT as measured, current_a and throttle (S,) with NaN where unknown; ``correction(b)`` batch b's
        calibration (offset (3,), matrix (3, 3)) or None; ``vehicles`` the vehicle each batch names ("" none), or
        None. Kept: ``compared_field`` of each. Devices outside any vehicle are skipped."""
        for b, device in enumerate(devices):
            vehicle = vehicle_of(device, "" if vehicles is None else vehicles[b])
            lo, hi = int(bounds[b]), int(bounds[b + 1])
            if vehicle is None or hi <= lo:
                continue
            field = compared_field(mag_ut[lo:hi], correction(b))
            rows = np.column_stack([t_ns[lo:hi] * 1e-9, field, current_a[lo:hi], throttle[lo:hi]])
            table = self.vehicles.get(vehicle)
            if table is None:
                table = self.vehicles[vehicle] = {}
            else:
                self.vehicles.touch(vehicle)
            table[device] = _append(table.get(device), rows)

    def series(self, vehicle: str) -> dict[str, Series]:
        """The vehicle's devices and their samples (empty when the vehicle is not known)."""
        from magnet.vehicle.consistency import Series  # the comparison's module, when a vehicle is judged

        table = self.vehicles.get(vehicle) or {}
        return {d: Series(r[:, 0], r[:, 1:4], r[:, 4], r[:, 5]) for d, r in sorted(table.items())}

    def known(self) -> list[str]:
        return sorted(self.vehicles)


def compared_field(mag_ut: np.ndarray, correction: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    """The field a compass is compared by (N, 3) uT: measured (N, 3) less its calibration's offset, times the
    symmetric part P of its matrix A = U P (polar decomposition): the soft iron corrected, but not a rotation a fit
    took up (the autopilot does not apply magnet's calibration, and a rotation found is what to tell it)."""
    if correction is None:
        return mag_ut
    offset, matrix = correction
    _, sizes, vt = np.linalg.svd(np.asarray(matrix, dtype=float))
    symmetric = vt.T @ np.diag(sizes) @ vt
    return (mag_ut - offset) @ symmetric.T


def _append(old: np.ndarray | None, rows: np.ndarray) -> np.ndarray:
    """``old`` with the rows of a new batch that start a new ``STEP_S`` slot (finite fields only), the newest
    ``MAX_ROWS`` within ``WINDOW_S`` of the last."""
    rows = rows[np.isfinite(rows[:, 1:4]).all(axis=1)]
    slots = np.floor(rows[:, 0] / STEP_S)
    last = -np.inf if old is None or not len(old) else float(np.floor(old[-1, 0] / STEP_S))
    first = np.concatenate([[True], slots[1:] != slots[:-1]]) & (slots > last)
    joined = rows[first] if old is None else np.vstack([old, rows[first]])
    if len(joined):
        joined = joined[joined[:, 0] >= joined[-1, 0] - WINDOW_S]
    return joined[-MAX_ROWS:]
