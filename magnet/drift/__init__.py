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
Modules: ``settings`` (``DriftSettings``, ``Reference``), ``alerts`` (``Alert`` and its one entry from the wire,
``alert_from_message``), ``tracker`` (``DriftTracker``, one device: windows, verdicts, hysteresis), ``monitor``
(``DriftMonitor``, many devices).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from magnet.drift.settings import DEFAULT_DRIFT, NS_PER_DAY, NS_PER_S, DriftSettings, Reference

if TYPE_CHECKING:
    from magnet.drift.alerts import (
        ADVICE,
        CLEARED_ADVICE,
        MAX_ADVICE_CHARS,
        Alert,
        AlertKind,
        advice_for,
        alert_from_message,
    )
    from magnet.drift.monitor import DriftMonitor
    from magnet.drift.tracker import DriftTracker, Verdict, robust_verdict

#: the alerts and the trackers, loaded on first use (PEP 562): the trackers bring numpy statistics and
#: ``magnet.quality``, the alerts an enum and the wire's limits, which the
#: commands that import the settings alone (``magnet heading`` through the compass's core) never run
_LAZY = {
    "ADVICE": "magnet.drift.alerts",  # the alerts (an enum, the wire's limits): where an alert is made or read
    "CLEARED_ADVICE": "magnet.drift.alerts",
    "MAX_ADVICE_CHARS": "magnet.drift.alerts",
    "Alert": "magnet.drift.alerts",
    "AlertKind": "magnet.drift.alerts",
    "advice_for": "magnet.drift.alerts",
    "alert_from_message": "magnet.drift.alerts",
    "DriftMonitor": "magnet.drift.monitor",
    "DriftTracker": "magnet.drift.tracker",
    "Verdict": "magnet.drift.tracker",
    "robust_verdict": "magnet.drift.tracker",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'magnet.drift' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


__all__ = [
    "ADVICE",
    "CLEARED_ADVICE",
    "DEFAULT_DRIFT",
    "MAX_ADVICE_CHARS",
    "NS_PER_DAY",
    "NS_PER_S",
    "Alert",
    "AlertKind",
    "DriftMonitor",
    "DriftSettings",
    "DriftTracker",
    "Reference",
    "Verdict",
    "advice_for",
    "alert_from_message",
    "robust_verdict",
]
