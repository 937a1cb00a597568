"""Collection of calibration samples: evenly spread over the sphere of directions, bounded, per device.

The direction of each raw reading from the running centre of the cloud (per-axis (max + min) / 2) falls in one of
``FINE_BANDS x FINE_SECTORS`` equal-area cells, and a sample is kept only when its cell is still empty (at most
``capacity`` samples). Pure numpy; the clock is the caller's (``now_s`` arguments).

A method that fits from the gyroscope (``Method.needs_gyroscope``: gyro-ellipsoid) needs consecutive samples in
time order with their rates, which the cells lose: its collection also keeps the device's recent samples in a
bounded ring (``magnet.calibration.sample_runs.RecentRuns``, at most ``run_capacity`` samples, 88 bytes each: 2.6 MB per
device at the default 30,000), cut into runs at every stall in ``t_ns`` or gap in ``seq``, and fits the longest run
with ``gyr=`` (``Run.turn_rads``: a sample after missing ones over all their periods) and ``period_s=`` (the run's
median step of ``t_ns``). The cells still give its coverage for progress.

``auto`` (``magnet.calibration.choose``) keeps the ring too, made on the first batch that carries the gyroscope (a
device without one costs what an ellipsoid collection costs): it fits ``fit_auto`` on the longest run once that run
holds ``MIN_SAMPLES`` of gyro-ellipsoid, else the ellipsoid on the cells; it is ready when either the run turned
enough or the cells are covered enough, and a batch without the gyroscope is never counted against it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from magnet.calibration import MIN_SAMPLES, FitError, FitInput, Method
from magnet.calibration.choose import AUTO, fit_choice, parse_choice
from magnet.calibration.course import MIN_ACCELERATING_S, accelerating_s
from magnet.calibration.sample_runs import RUN_CAPACITY, RecentRuns, Run
from magnet.model import Calibration
from magnet.quality import Coverage, coverage

FINE_BANDS = 24  # equal-area bands in z (uniform in z = equal area on the sphere) ...
FINE_SECTORS = 48  # ... times sectors in longitude: 1152 fine cells, one kept sample each
REBIN_SHIFT_UT = 2.0  # re-sort kept samples into cells when the cloud's centre moved this far
FIT_EVERY_NEW = 25  # fit again after this many newly kept samples
FIT_INTERVAL_S = 0.5
#: a run is fitted from the gyroscope once it turned this far about at least two body axes (deg)
READY_TURN_DEG = 90.0
#: ... or, for auto (whose field ladder fits a device that only yaws and judges for itself whether the turns identify
#: the offset: ``magnet.calibration.field``), this far about one axis: a sixth of a turn (rates under TURNING_RADS do
#: not count, so a boat's slow turns count less than its heading moved; with 90 the boat of tuning seed 19 waited
#: from 57.5 to 77 s, its fit at 57.5 s identified)
PLANAR_READY_TURN_DEG = 60.0
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

    method: the fit method, or "auto"; session: an operator's session (else automatic collection); a method that
    needs the gyroscope also keeps ``runs``, the last ``run_capacity`` samples in time order (None for the others;
    for auto, None until a batch carries the gyroscope)."""

    def __init__(self, method: str, session: bool, capacity: int, run_capacity: int = RUN_CAPACITY) -> None:
        self.method, self.session, self.capacity = parse_choice(method), session, capacity
        self.auto = self.method == AUTO
        self.in_service = False  # a refresh of a calibrated device (``magnet.calibrator.refresh``)
        self.travelled = False  # its device moved over the ground meanwhile (``magnet.calibrator.refresh.travels``)
        self.window_s: float | None = None  # fit only the last this many seconds of the run (None: all of it)
        self.tried_ns = -(2**62)  # a refresh's last try: the time of the newest sample then (ns)
        self.changed_batches = 0  # a refresh: batches in a row whose field strength the record in force misses
        self.changed_since_ns = 0  # ... the time of the first sample of the first of them (ns)
        self.after_change = False  # a refresh collection made after the device's iron changed
        self.iron_watch: Any = None  # a refresh: its iron's watch (``magnet.calibrator.iron_moved.IronWatch``)
        self.run_capacity = run_capacity
        self.runs = None if self.auto or not Method.parse(self.method).needs_gyroscope else RecentRuns(run_capacity)
        self.no_gyroscope = 0  # batches that came without the gyroscope this collection's method needs
        self.last_fit_written = 0
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

    def add(
        self,
        mag: np.ndarray,
        acc: np.ndarray | None,
        gyr_rads: np.ndarray | None = None,
        t_ns: np.ndarray | None = None,
        seq: int = 0,
        vel_ned_ms: np.ndarray | None = None,
    ) -> int:
        """Keep the samples of a batch (mag (N, 3) uT, acc (N, 3) or None) whose fine cell is still empty; returns
        how many were kept. With ``runs``: the batch's gyr_rads (N, 3) rad/s, t_ns (N,) int ns and number ``seq``
        go to the ring too (with vel_ned_ms (N, 3) m/s, the velocity over the ground, or None); a batch without
        them is counted in ``no_gyroscope`` and said in ``last_reason`` (not for auto, whose ring is made by the
        first batch with them)."""
        if self.auto and self.runs is None and gyr_rads is not None and t_ns is not None:
            self.runs = RecentRuns(self.run_capacity)
        if self.runs is not None:
            self._add_run(self.runs, mag, acc, gyr_rads, t_ns, seq, vel_ned_ms)
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

    def _add_run(
        self,
        runs: RecentRuns,
        mag: np.ndarray,
        acc: np.ndarray | None,
        gyr: np.ndarray | None,
        t_ns: np.ndarray | None,
        seq: int,
        vel_ned_ms: np.ndarray | None = None,
    ) -> None:
        if gyr is None or t_ns is None:
            if self.auto:
                return  # the cells still take the batch; the fit goes by them when the runs are too short
            self.no_gyroscope += 1
            self.last_reason = (
                f"{self.method} needs a gyroscope: {self.no_gyroscope} raw batch(es) of this device came without "
                "gyr_rads (send the gyroscope's rates, or calibrate with ellipsoid)"
            )
            return
        runs.add(mag, acc, gyr, t_ns, seq, vel_ned_ms)

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

    def turn_wait(self, min_samples: int) -> str:
        """With ``runs``: why the longest run is not worth fitting yet ("" when it is): fewer than ``min_samples``
        samples, or a turn of less than ``READY_TURN_DEG`` about a second body axis (the fit needs turns about more
        than one axis, and refuses anything less at the cost of a fit)."""
        run = None if self.runs is None else self.runs.longest()
        if run is None or len(run) < min_samples:
            if self.no_gyroscope and self.last_reason:
                return self.last_reason
            return f"{0 if run is None else len(run)} of {min_samples} consecutive samples with the gyroscope"
        turned = run.turned_deg()
        if np.sort(turned)[-2] >= READY_TURN_DEG or (self.auto and turned.max() >= PLANAR_READY_TURN_DEG):
            return ""
        if (
            self.auto
            and run.vel_ned_ms is not None
            and accelerating_s(run.vel_ned_ms, run.period_s) >= (MIN_ACCELERATING_S)
        ):  # the velocity's accelerations tell the heading as turns would (the course fit: docs/field-calibration.md)
            return ""
        return (
            f"turned {turned[0]:.0f}, {turned[1]:.0f}, {turned[2]:.0f} deg about x, y, z over the last "
            f"{len(run) * run.period_s:.0f} s: turn the device about every axis"
        )

    def postpone(self, now_s: float, reason: str) -> None:
        """Not ready to fit: keep ``reason`` and wait for as many new samples as after a fit."""
        self.last_reason = reason
        self.last_fit_kept, self.last_fit_s = self.kept, now_s
        self.last_fit_written = 0 if self.runs is None else self.runs.written

    def fit(
        self,
        field_ut: float | None,
        now_s: float,
        reference: Calibration | None = None,
        dip_deg: float | None = None,
        declination_deg: float | None = None,
    ) -> Calibration | None:
        """Fit the kept samples (records the result or the reason); None when no calibration can be computed.

        field_ut: the expected |B| in uT or None; dip_deg: the expected dip (deg) or None (the field ladder's
        prior); reference: the calibration in force, which the fit must beat (None: none). With ``runs``: the
        longest run with the gyroscope; for auto, only once it holds gyro-ellipsoid's ``MIN_SAMPLES`` (else the
        cells, by the ellipsoid)."""
        self.last_fit_kept, self.last_fit_s = self.kept, now_s
        run = None
        if self.runs is not None:
            self.last_fit_written = self.runs.written
            run = self.runs.longest()
            if run is not None and self.window_s is not None:
                run = run.tail(self.window_s)
        try:
            if self.runs is None or (self.auto and (run is None or len(run) < MIN_SAMPLES[Method.GYRO_ELLIPSOID])):
                mag, acc = self.samples()
                data = FitInput(mag, acc=acc, field_ut=field_ut, reference=reference, dip_deg=dip_deg)
                self.last_fit = fit_choice(data, self.method)
            else:
                self.last_fit = _fit_run(run, self.method, field_ut, reference, dip_deg, declination_deg)
        except FitError as exc:
            self.last_fit, self.last_reason = None, str(exc)
            return None
        self.last_reason = self.last_fit.reason
        return self.last_fit

    def due(self, min_samples: int, now_s: float) -> bool:
        """Whether to fit again: enough samples, enough new ones since the last fit, and not too soon. With
        ``runs``: the ring holds ``min_samples``, and a quarter as many new ones as it holds came since the last
        try (the cost of fitting a growing ring stays a few fits' worth per sample)."""
        if now_s - self.last_fit_s < FIT_INTERVAL_S:
            return False
        if self.runs is None:
            return self.kept >= min_samples and self.kept - self.last_fit_kept >= FIT_EVERY_NEW
        fresh = self.runs.written - self.last_fit_written
        return self.runs.held >= min_samples and fresh >= max(FIT_EVERY_NEW, self.runs.held // 4)


def _fit_run(
    run: Run | None,
    method: str,
    field_ut: float | None,
    reference: Calibration | None = None,
    dip_deg: float | None = None,
    declination_deg: float | None = None,
) -> Calibration:
    """Fit the consecutive samples of ``run`` with the gyroscope (``method``: gyro-ellipsoid or auto); FitError when
    there is none."""
    if run is None:
        raise FitError(f"{method} has no consecutive samples with the gyroscope yet: keep the device sending")
    data = FitInput(
        run.mag,
        t_s=run.t_ns * 1e-9,
        acc=run.acc,
        gyr_rads=run.turn_rads,
        period_s=run.period_s,
        field_ut=field_ut,
        reference=reference,
        dip_deg=dip_deg,
        vel_ned_ms=run.vel_ned_ms,
        declination_deg=declination_deg,
    )
    return fit_choice(data, method)
