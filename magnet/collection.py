"""Collection of calibration samples: evenly spread over the sphere of directions, bounded, per device.

The direction of each raw reading from the running centre of the cloud (per-axis (max + min) / 2) falls in one of
``FINE_BANDS x FINE_SECTORS`` equal-area cells, and a sample is kept only when its cell is still empty (at most
``capacity`` samples). Pure numpy; the clock is the caller's (``now_s`` arguments).
"""

from __future__ import annotations

import numpy as np

from magnet.calibration import FitError, fit
from magnet.model import Calibration
from magnet.quality import Coverage, coverage

FINE_BANDS = 24  # equal-area bands in z (uniform in z = equal area on the sphere) ...
FINE_SECTORS = 48  # ... times sectors in longitude: 1152 fine cells, one kept sample each
REBIN_SHIFT_UT = 2.0  # re-sort kept samples into cells when the cloud's centre moved this far
FIT_EVERY_NEW = 25  # fit again after this many newly kept samples
FIT_INTERVAL_S = 0.5
INITIAL_ROOM = 64  # samples' arrays start this small and double up to the capacity (a device that sends one
# batch costs kilobytes, not the capacity's worth)


def fine_cells(directions: np.ndarray) -> np.ndarray:
    """Fine equal-area cell index (N,) of directions (N, 3) (any length > 0)."""
    unit = directions / np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-300)
    band = np.minimum(((unit[:, 2] + 1.0) * 0.5 * FINE_BANDS).astype(int), FINE_BANDS - 1)
    sector = np.minimum(
        ((np.arctan2(unit[:, 1], unit[:, 0]) + np.pi) / (2 * np.pi) * FINE_SECTORS).astype(int), FINE_SECTORS - 1
    )
    return band * FINE_SECTORS + sector


class Collection:
    """Evenly spread samples of one device: mag (K, 3) uT and acc (K, 3) m/s^2 (or none), K <= capacity.

    method: the fit method; session: an operator's session (else automatic collection)."""

    def __init__(self, method: str, session: bool, capacity: int) -> None:
        self.method, self.session, self.capacity = method, session, capacity
        self.mag = np.empty((min(capacity, INITIAL_ROOM), 3))
        self.acc = np.empty((min(capacity, INITIAL_ROOM), 3))
        self.has_acc = True
        self.kept = self.seen = 0
        self.occupied = np.zeros(FINE_BANDS * FINE_SECTORS, dtype=bool)
        self.lo = np.full(3, np.inf)
        self.hi = np.full(3, -np.inf)
        self.binned_centre: np.ndarray | None = None
        self.last_fit_kept = 0
        self.last_fit_s = -np.inf
        self.last_fit: Calibration | None = None
        self.last_reason = ""

    @property
    def centre(self) -> np.ndarray:
        """Running centre of the raw cloud, (max + min) / 2 per axis, uT (zeros before any sample)."""
        return (self.lo + self.hi) / 2 if self.seen else np.zeros(3)

    def add(self, mag: np.ndarray, acc: np.ndarray | None) -> int:
        """Keep the samples of a batch (mag (N, 3) uT, acc (N, 3) or None) whose fine cell is still empty; returns
        how many were kept."""
        self.seen += len(mag)
        self.lo = np.minimum(self.lo, mag.min(axis=0))
        self.hi = np.maximum(self.hi, mag.max(axis=0))
        if acc is None:
            self.has_acc = False
        centre = self.centre
        if self.binned_centre is None or np.abs(centre - self.binned_centre).max() > REBIN_SHIFT_UT:
            self._rebin(centre)
        room = self.capacity - self.kept
        if room <= 0:
            return 0
        cells = fine_cells(mag - centre)
        unique, first = np.unique(cells, return_index=True)
        new = first[~self.occupied[unique]][:room]
        if new.size == 0:
            return 0
        self.occupied[cells[new]] = True
        self._room_for(self.kept + new.size)
        self.mag[self.kept : self.kept + new.size] = mag[new]
        if acc is not None:
            self.acc[self.kept : self.kept + new.size] = acc[new]
        self.kept += new.size
        return int(new.size)

    def _room_for(self, size: int) -> None:
        """Grow the sample arrays (doubling, at most to the capacity) so that they hold ``size`` samples."""
        if size <= len(self.mag):
            return
        rows = min(self.capacity, max(size, 2 * len(self.mag)))
        grow = np.empty((rows - len(self.mag), 3))
        self.mag, self.acc = np.concatenate([self.mag, grow]), np.concatenate([self.acc, grow])

    def _rebin(self, centre: np.ndarray) -> None:
        """Sort the kept samples into cells around the new centre, keeping the first of each cell."""
        self.binned_centre = centre
        self.occupied[:] = False
        if not self.kept:
            return
        cells = fine_cells(self.mag[: self.kept] - centre)
        unique, first = np.unique(cells, return_index=True)
        first = np.sort(first)
        self.mag[: first.size] = self.mag[first]
        self.acc[: first.size] = self.acc[first]
        self.kept = int(first.size)
        self.occupied[unique] = True

    def samples(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The kept samples: mag (K, 3) uT and acc (K, 3) m/s^2, or None when a batch came without acc."""
        return self.mag[: self.kept], (self.acc[: self.kept] if self.has_acc else None)

    def coverage(self) -> Coverage:
        return coverage(self.mag[: self.kept] - self.centre)

    def fit(self, field_ut: float | None, now_s: float) -> Calibration | None:
        """Fit the kept samples (records the result or the reason); None when no calibration can be computed.

        field_ut: the expected |B| in uT or None."""
        self.last_fit_kept, self.last_fit_s = self.kept, now_s
        mag, acc = self.samples()
        try:
            self.last_fit = fit(mag, self.method, acc=acc, unit="ut", field_ut=field_ut)
        except FitError as exc:
            self.last_fit, self.last_reason = None, str(exc)
            return None
        self.last_reason = self.last_fit.reason
        return self.last_fit

    def due(self, min_samples: int, now_s: float) -> bool:
        """Whether to fit again: enough samples, enough new ones since the last fit, and not too soon."""
        return (
            self.kept >= min_samples
            and self.kept - self.last_fit_kept >= FIT_EVERY_NEW
            and now_s - self.last_fit_s >= FIT_INTERVAL_S
        )
