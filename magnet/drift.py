"""Drift alerts: does a device's calibrated field still look like the one its calibration was made in?

The compass feeds every calibrated sample of a device (its |B| in uT and, with an accelerometer, its dip in degrees)
to that device's ``DriftTracker``. Samples are grouped in windows of ``window_s`` seconds of the device's own clock;
each window is judged on robust statistics (medians), so a passing truck or a motor burst that spoils less than half
of a window moves nothing, and a window that does depart counts only as one of ``raise_windows`` in a row:

- field strength: the median absolute departure of |B| from the calibration's own reference (its
  ``field_strength``), against ``max(strength_tol_pct % of it, strength_residual_factor x the fit's residual)``; and
  the median |B| against the World Magnetic Model's |B| at the device's place (``model_strength_tol_ut``, PX4's
  0.2 G). A hard-iron change on a turning device shows as |B| wandering around the reference (the median absolute
  departure), on a still one as a shifted level; both count.
- dip: the median absolute departure of the dip from the calibration's own reference (the median dip of its first
  ``raise_windows`` judged windows) against ``dip_tol_deg``; and the median dip against the model's inclination
  (``model_dip_tol_deg``, PX4's 20 deg).
- calibration age: older than ``max_age_days``.

Hysteresis: an alert opens after ``raise_windows`` departed windows in a row (departure ratio > 1) and clears after
``clear_windows`` windows in a row below ``clear_fraction`` of the thresholds; a new calibration clears everything
and starts afresh. A sustained change is therefore reported within ``DriftSettings.detection_bound_s`` =
(raise_windows + 1) x window_s of device time (the window it starts in may not count). Pure numpy, no clock: time
is the samples' ``t_ns``.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from typing import Any

import numpy as np

NS_PER_S = 1_000_000_000
NS_PER_DAY = 86_400 * NS_PER_S


class AlertKind(enum.Enum):
    """What drifted (the alert message's ``kind``)."""

    FIELD_STRENGTH = "field_strength"
    DIP = "dip"
    CALIBRATION_AGE = "calibration_age"


ADVICE = {
    AlertKind.FIELD_STRENGTH: (
        "the calibrated field strength departs from {ref}: look for new iron or a motor near "
        "the sensor, a bent mount or a swapped part, then recalibrate"
    ),
    AlertKind.DIP: (
        "the calibrated dip angle departs from {ref}: look for new iron near the sensor or a moved "
        "mount (magnetometer turned against the accelerometer), then recalibrate"
    ),
    AlertKind.CALIBRATION_AGE: "the calibration is older than {ref}: recalibrate (magnet calibrate DEVICE start)",
}


@dataclasses.dataclass(frozen=True)
class DriftSettings:
    """Thresholds of the drift alerts (see the module docstring); every field a positive number."""

    window_s: float = 30.0
    raise_windows: int = 4
    clear_windows: int = 4
    clear_fraction: float = 0.5
    strength_tol_pct: float = 6.0
    strength_residual_factor: float = 3.0
    model_strength_tol_ut: float = 20.0
    dip_tol_deg: float = 4.0
    model_dip_tol_deg: float = 20.0
    max_age_days: float = 365.0
    min_window_samples: int = 20
    max_window_samples: int = 4096

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"drift setting {field.name} must be a positive number, got {value!r}")
        for name in ("raise_windows", "clear_windows", "min_window_samples", "max_window_samples"):
            if not isinstance(getattr(self, name), int):
                raise ValueError(f"drift setting {name} must be a whole number")
        if self.clear_fraction >= 1:
            raise ValueError(f"clear_fraction must be below 1 (hysteresis), got {self.clear_fraction}")

    @property
    def window_ns(self) -> int:
        """Window length in ns."""
        return round(self.window_s * NS_PER_S)

    @property
    def detection_bound_s(self) -> float:
        """Longest device time from the start of a sustained departure to its alert (data flowing)."""
        return (self.raise_windows + 1) * self.window_s


#: the defaults, documented in the README
DEFAULT_DRIFT = DriftSettings()


@dataclasses.dataclass(frozen=True)
class Reference:
    """What a device's field should look like: the calibration's |B| (uT; None or 0: learn it like the dip), its
    fit residual (uT), the model's |B| (uT) and inclination (deg) at the device's place (None: unknown), and the
    calibration's id and ``created_ns``."""

    strength_ut: float | None
    residual_ut: float = 0.0
    model_total_ut: float | None = None
    model_dip_deg: float | None = None
    created_ns: int = 0
    calibration_id: str = ""


@dataclasses.dataclass(frozen=True)
class Alert:
    """One alert event. ``since_ns``: when the departure (or, cleared, the recovery) began; measured and expected in
    uT (field_strength), degrees (dip) or days (calibration_age)."""

    device: str
    kind: AlertKind
    since_ns: int
    measured: float
    expected: float
    advice: str
    cleared: bool = False

    def to_message(self) -> dict[str, Any]:
        """The ``<prefix>/<device>/alert`` map: v, device, kind, since_ns, measured, expected, advice (+ cleared)."""
        out: dict[str, Any] = {
            "v": 1,
            "device": self.device,
            "kind": self.kind.value,
            "since_ns": int(self.since_ns),
            "measured": round(float(self.measured), 4),
            "expected": round(float(self.expected), 4),
            "advice": self.advice,
        }
        if self.cleared:
            out["cleared"] = True
        return out


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
    median = float(np.median(values))
    departure = float(np.median(np.abs(values - reference)))
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
        """|B| (uT) and dip (deg) samples, the last of them at ``last_ns``."""
        self.last_ns = max(self.last_ns, last_ns)
        if self.stride > 1:
            strength, dip = strength[:: self.stride], dip[:: self.stride]
        self.strength.append(strength)
        self.dip.append(dip)
        self.count += strength.size
        if self.count > self.cap:
            joined_s, joined_d = np.concatenate(self.strength)[::2], np.concatenate(self.dip)[::2]
            self.strength, self.dip, self.count, self.stride = [joined_s], [joined_d], joined_s.size, self.stride * 2

    def values(self) -> tuple[np.ndarray, np.ndarray]:
        """Finite |B| values and finite dip values of the window."""
        strength = np.concatenate(self.strength) if self.strength else np.empty(0)
        dip = np.concatenate(self.dip) if self.dip else np.empty(0)
        return strength[np.isfinite(strength)], dip[np.isfinite(dip)]


class DriftTracker:
    """The drift state of one device under one calibration (see the module docstring). ``add`` takes samples in
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
        unit = "uT" if kind is AlertKind.FIELD_STRENGTH else "deg"
        advice = ADVICE[kind].format(ref=f"{verdict.expected:.1f} {unit}")
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
        advice = ADVICE[AlertKind.CALIBRATION_AGE].format(ref=f"{self.settings.max_age_days:g} days")
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


class DriftMonitor:
    """The drift trackers of many devices: one per device with a calibration in force. Bounded by the devices the
    caller feeds (the compass's calibrations)."""

    def __init__(self, settings: DriftSettings = DEFAULT_DRIFT) -> None:
        self.settings = settings
        self.trackers: dict[str, DriftTracker] = {}

    def calibration(self, device: str, reference: Reference, now_ns: int) -> list[Alert]:
        """A calibration came into force for ``device``: clear its open alerts and start afresh."""
        old = self.trackers.get(device)
        if old is not None and old.reference.calibration_id == reference.calibration_id:
            old.set_model(reference.model_total_ut, reference.model_dip_deg)
            return []
        events = [] if old is None else old.clear_all(now_ns, f"calibration {reference.calibration_id} in force")
        self.trackers[device] = DriftTracker(device, reference, self.settings)
        return events

    def add(self, device: str, t_ns: np.ndarray, strength_ut: np.ndarray, dip_deg: np.ndarray) -> list[Alert]:
        tracker = self.trackers.get(device)
        return [] if tracker is None else tracker.add(t_ns, strength_ut, dip_deg)

    def add_columns(
        self, devices: list[str], bounds: list[int], t_ns: np.ndarray, strength_ut: np.ndarray, dip_deg: np.ndarray
    ) -> list[Alert]:
        """``add`` for B batches at once: devices (B,), bounds (B + 1) sample offsets, t_ns, strength_ut, dip_deg
        (S,). The window of every sample is computed once; a batch inside its device's current window is appended
        without further numpy work."""
        if not devices:
            return []
        index = t_ns // self.settings.window_ns
        starts, ends = np.asarray(bounds[:-1]), np.asarray(bounds[1:]) - 1
        first, last, last_ns = index[starts].tolist(), index[ends].tolist(), t_ns[ends].tolist()
        events: list[Alert] = []
        for i, device in enumerate(devices):
            tracker = self.trackers.get(device)
            if tracker is None:
                continue
            lo, hi = bounds[i], bounds[i + 1]
            if first[i] != last[i] or not tracker.add_within(first[i], last_ns[i], strength_ut[lo:hi], dip_deg[lo:hi]):
                events += tracker.add(t_ns[lo:hi], strength_ut[lo:hi], dip_deg[lo:hi])
        return events

    def open_alerts(self) -> list[Alert]:
        return [alert for tracker in self.trackers.values() for alert in tracker.open_alerts]


MAX_ADVICE_CHARS = 1_000


def alert_from_message(message: Any) -> Alert:
    """The one entry of an alert map from outside (``<prefix>/<device>/alert``): ValueError naming what is wrong.
    The device id is the caller's to check (``magnet.wire.message_device``)."""
    if not isinstance(message, dict):
        raise ValueError("an alert must be a map")
    if message.get("v") != 1:
        raise ValueError(f"alert schema version {message.get('v')!r}, expected 1")
    try:
        kind = AlertKind(message.get("kind"))
    except ValueError:
        raise ValueError(f"alert kind must be one of {', '.join(k.value for k in AlertKind)}") from None
    since = message.get("since_ns")
    if isinstance(since, bool) or not isinstance(since, int) or since < 0:
        raise ValueError("alert since_ns must be a whole number of ns >= 0")
    numbers: list[Any] = [message.get("measured"), message.get("expected")]
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) for x in numbers):
        raise ValueError("alert measured and expected must be finite numbers")
    advice, cleared = message.get("advice"), message.get("cleared", False)
    if not isinstance(advice, str) or len(advice) > MAX_ADVICE_CHARS:
        raise ValueError(f"alert advice must be text of at most {MAX_ADVICE_CHARS} characters")
    if not isinstance(cleared, bool):
        raise ValueError("alert cleared must be true or false")
    return Alert(str(message.get("device")), kind, since, float(numbers[0]), float(numbers[1]), advice, cleared)
