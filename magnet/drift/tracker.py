"""The drift state of one device under one calibration: windows of samples, robust verdicts, hysteresis."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from magnet.drift.alerts import Alert, AlertKind, advice_for
from magnet.drift.settings import DEFAULT_DRIFT, NS_PER_DAY, DriftSettings, Reference
from magnet.quality.stats import median as median_of


@dataclasses.dataclass(frozen=True)
class Verdict:
    """One window's judgement of one quantity: ratio > 1 departed, < clear_fraction recovered; measured and
    expected as reported."""

    ratio: float
    measured: float
    expected: float


@dataclasses.dataclass
class _Hysteresis:
    """Streak counting for one alert kind."""

    open: Alert | None = None
    streak: int = 0
    streak_start_ns: int = 0

    def step(self, ratio: float, start_ns: int, settings: DriftSettings) -> bool:
        """Count one judged window; True when the alert opens or clears now."""
        moving = ratio > 1.0 if self.open is None else ratio < settings.clear_fraction
        if not moving:
            self.streak = 0
            return False
        if self.streak == 0:
            self.streak_start_ns = start_ns
        self.streak += 1
        return self.streak >= (settings.raise_windows if self.open is None else settings.clear_windows)


def robust_verdict(
    values: np.ndarray, reference: float, tolerance: float, model: float | None, model_tolerance: float
) -> Verdict | None:
    """Judge one window of one quantity (values (N,), finite) against its reference (own tolerance) and the model.

    Own: median |value - reference| / tolerance, reported as reference +- that departure (the side the median lies
    on). Model: |median - model| / model_tolerance, reported as the median. The larger ratio wins."""
    if values.size == 0:
        return None
    median = median_of(values)  # one partition each: the same numbers as np.median, several times faster
    departure = median_of(np.abs(values - reference))
    typical = reference + math.copysign(departure, median - reference)
    verdict = Verdict(departure / tolerance, typical, reference)
    if model is not None and model_tolerance > 0:
        against_model = Verdict(abs(median - model) / model_tolerance, median, model)
        if against_model.ratio > verdict.ratio:
            return against_model
    return verdict


class _Window:
    """The samples of one window: |B| (uT) and dip (deg, NaN without acc), decimated by 2 whenever more than
    ``cap`` are held (bounded memory, still spread over the whole window)."""

    def __init__(self, index: int, cap: int) -> None:
        self.index, self.cap, self.stride = index, cap, 1
        self.strength: list[np.ndarray] = []
        self.dip: list[np.ndarray] = []
        self.count = 0
        self.last_ns = 0

    def add(self, strength: np.ndarray, dip: np.ndarray, last_ns: int) -> None:
        """|B| (uT) and dip (deg) samples, the last of them at ``last_ns``: copied, never kept as views (a batch's
        samples are a slice of its whole drain's arrays, which a view would keep alive until the window closes, and
        for good in the last window of a device that stopped: docs/front-door.md, "Memory per service")."""
        self.last_ns = max(self.last_ns, last_ns)
        strength, dip = strength[:: self.stride].copy(), dip[:: self.stride].copy()
        self.strength.append(strength)
        self.dip.append(dip)
        self.count += strength.size
        if self.count > self.cap:
            joined_s, joined_d = np.concatenate(self.strength)[::2].copy(), np.concatenate(self.dip)[::2].copy()
            self.strength, self.dip, self.count, self.stride = [joined_s], [joined_d], joined_s.size, self.stride * 2

    def values(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite |B| values and finite dip values of the window."""
        strength = np.concatenate(self.strength) if self.strength else np.empty(0)
        dip = np.concatenate(self.dip) if self.dip else np.empty(0)
        return strength[np.isfinite(strength)], dip[np.isfinite(dip)]


class DriftTracker:
    """The drift state of one device under one calibration (see ``magnet.drift``). ``add`` takes samples in
    time order and returns the alerts that open or clear; ``open_alerts`` the ones open now."""

    def __init__(self, device: str, reference: Reference, settings: DriftSettings = DEFAULT_DRIFT) -> None:
        self.device, self.reference, self.settings = device, reference, settings
        self.state = {kind: _Hysteresis() for kind in AlertKind}
        self.window: _Window | None = None
        strength = reference.strength_ut if reference.strength_ut else None
        self.own: dict[AlertKind, float | None] = {AlertKind.FIELD_STRENGTH: strength, AlertKind.DIP: None}
        self.baseline: dict[AlertKind, list[float]] = {AlertKind.FIELD_STRENGTH: [], AlertKind.DIP: []}
        self.windows_judged = 0

    @property
    def open_alerts(self) -> list[Alert]:
        return [s.open for s in self.state.values() if s.open is not None]

    def set_model(self, model_total_ut: float | None, model_dip_deg: float | None) -> None:
        """The device's place changed: judge against the model there from now on."""
        self.reference = dataclasses.replace(self.reference, model_total_ut=model_total_ut, model_dip_deg=model_dip_deg)

    def add(self, t_ns: np.ndarray, strength_ut: np.ndarray, dip_deg: np.ndarray) -> list[Alert]:
        """Samples t_ns (N,) int ns, strength_ut (N,) calibrated |B| in uT, dip_deg (N,) deg (NaN without acc), in
        time order; the alerts opened or cleared by the windows they complete."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if t_ns.size == 0:
            return []
        index = t_ns // self.settings.window_ns
        events: list[Alert] = []
        if self.window is None:
            self.window = _Window(int(index[0]), self.settings.max_window_samples)
        lo = 0
        while lo < t_ns.size:
            later = np.flatnonzero(index[lo:] > self.window.index)
            hi = t_ns.size if later.size == 0 else lo + int(later[0])
            if hi > lo:
                self.window.add(strength_ut[lo:hi], dip_deg[lo:hi], int(t_ns[hi - 1]))
            if hi == t_ns.size:
                break
            events += self._close(self.window)
            self.window = _Window(int(index[hi]), self.settings.max_window_samples)
            lo = hi
        return events

    def add_within(self, index: int, last_ns: int, strength_ut: np.ndarray, dip_deg: np.ndarray) -> bool:
        """The fast path of ``add`` for samples that all fall in window ``index``: True when they did belong to the
        current window and were taken, False (nothing taken) otherwise."""
        window = self.window
        if window is None or window.index != index:
            return False
        window.add(strength_ut, dip_deg, last_ns)
        return True

    def _close(self, window: _Window) -> list[Alert]:
        """Judge a finished window; the alerts it opens or clears."""
        s = self.settings
        start_ns = window.index * s.window_ns
        events = self._age(window.last_ns)
        strength, dip = window.values()
        verdicts = {
            AlertKind.FIELD_STRENGTH: self._judge(AlertKind.FIELD_STRENGTH, strength),
            AlertKind.DIP: self._judge(AlertKind.DIP, dip),
        }
        self.windows_judged += 1
        for kind, verdict in verdicts.items():
            if verdict is not None:
                events += self._step(kind, verdict, start_ns)
        return events

    def _judge(self, kind: AlertKind, values: np.ndarray) -> Verdict | None:
        s, ref = self.settings, self.reference
        if values.size < s.min_window_samples:
            return None
        own = self.own[kind]
        if own is None:  # still learning the calibration's own reference from its first windows
            self.baseline[kind].append(float(np.median(values)))
            if len(self.baseline[kind]) >= s.raise_windows:
                self.own[kind] = float(np.median(self.baseline[kind]))
        strength_ref = self.own[AlertKind.FIELD_STRENGTH] or ref.model_total_ut or 0.0
        if kind is AlertKind.FIELD_STRENGTH:
            tolerance = max(s.strength_tol_pct / 100.0 * (own or 0.0), s.strength_residual_factor * ref.residual_ut)
            model, model_tol = ref.model_total_ut, s.model_strength_tol_ut
        else:
            spread = math.degrees(s.strength_residual_factor * ref.residual_ut / strength_ref) if strength_ref else 0
            tolerance, model, model_tol = max(s.dip_tol_deg, spread), ref.model_dip_deg, s.model_dip_tol_deg
        if own is None:
            if model is None:
                return None
            return robust_verdict(values, model, math.inf, model, model_tol)
        return robust_verdict(values, own, tolerance, model, model_tol)

    def _step(self, kind: AlertKind, verdict: Verdict, start_ns: int) -> list[Alert]:
        state = self.state[kind]
        if not state.step(verdict.ratio, start_ns, self.settings):
            return []
        advice = advice_for(kind, verdict.expected)
        alert = Alert(
            self.device,
            kind,
            state.streak_start_ns,
            verdict.measured,
            verdict.expected,
            advice,
            cleared=state.open is not None,
        )
        state.open = None if alert.cleared else alert
        state.streak = 0
        return [alert]

    def _age(self, now_ns: int) -> list[Alert]:
        state = self.state[AlertKind.CALIBRATION_AGE]
        max_ns = int(self.settings.max_age_days * NS_PER_DAY)
        if state.open is not None or not self.reference.created_ns or now_ns - self.reference.created_ns <= max_ns:
            return []
        days = (now_ns - self.reference.created_ns) / NS_PER_DAY
        advice = advice_for(AlertKind.CALIBRATION_AGE, self.settings.max_age_days)
        state.open = Alert(
            self.device,
            AlertKind.CALIBRATION_AGE,
            self.reference.created_ns + max_ns,
            days,
            self.settings.max_age_days,
            advice,
        )
        return [state.open]

    def clear_all(self, now_ns: int, why: str) -> list[Alert]:
        """Clear every open alert (a new calibration came into force): the cleared events."""
        events = [
            dataclasses.replace(alert, since_ns=int(now_ns), cleared=True, advice=why) for alert in self.open_alerts
        ]
        for state in self.state.values():
            state.open, state.streak = None, 0
        return events
