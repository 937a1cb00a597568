"""The magnetic gain chosen from the gyroscope's drift (``magnet.attitude.mag_gain``) and a new record's heading taken
from the last seconds of field (``CausalDrift.heading_from_history``)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import vqf

from magnet.attitude import causal_drift as cd
from magnet.attitude import mag_gain as mg


class _Filter:
    """What ``MagneticGain`` asks of vqf: its delta (rad), kMagInit, its tauMag (s) read and set."""

    def __init__(self) -> None:
        self.delta = 0.0
        self.state = {"kMagInit": 0.0}
        self.params = {"tauMag": 9.0}

    def getDelta(self) -> float:  # noqa: N802 (vqf's name)
        return self.delta

    def setTauMag(self, tau: float) -> None:  # noqa: N802
        self.params["tauMag"] = tau


def _run(drift_dps: float, noise_deg: float, seconds: float = 120.0) -> list[float]:
    """tauMag (s) after each batch of 0.5 s for a delta drifting at ``drift_dps`` with white noise."""
    filter_ = _Filter()
    gain = mg.MagneticGain(filter_, 9.0)
    rng = np.random.default_rng(1)
    taus = []
    for t in np.arange(0.5, seconds, 0.5):
        filter_.delta = math.remainder(
            math.radians(drift_dps * t + 100.0 + noise_deg * rng.standard_normal()), 2.0 * math.pi
        )
        taus.append(gain.note(float(t), 0.02))
        assert filter_.params["tauMag"] == taus[-1]
    return taus


def test_a_gyroscope_that_does_not_drift_gets_a_longer_magnetic_time_constant() -> None:
    taus = _run(0.0, 0.5)
    assert all(tau == 9.0 for tau in taus[: int(mg.MIN_SPAN_S / 0.5) - 1])  # nothing before the span
    assert taus[-1] > 20.0
    assert max(taus) <= mg.MAX_TAU_S
    assert all(later / earlier <= mg.STEP + 1e-12 for earlier, later in itertools.pairwise(taus))


def test_a_drifting_gyroscope_keeps_vqfs_time_constant_and_a_reset_restores_it() -> None:
    assert all(tau == 9.0 for tau in _run(0.3, 0.5))  # 0.3 deg/s: 2.7 deg over 9 s, more than the field's error
    filter_ = _Filter()
    gain = mg.MagneticGain(filter_, 9.0)
    for t in np.arange(0.5, 100.0, 0.5):
        gain.note(float(t), 0.02)
    assert filter_.params["tauMag"] > 9.0
    gain.reset()
    assert filter_.params["tauMag"] == 9.0 and gain.tau_s == 9.0
    filter_.state["kMagInit"] = 0.5  # vqf takes its first heading: no row
    assert gain.note(200.0, 0.02) == 9.0 and gain.t0 is None


def _history(angle_deg: float, disturbed: slice | None = None) -> tuple[cd.CausalDrift, np.ndarray]:
    """A level device (vqf's 6D attitude the identity) whose corrected field points ``angle_deg`` clockwise from the
    6D frame's north, 20 s of history rows at 0.5 s with 1 deg of noise; rows ``disturbed`` with an object's field
    added (|B| 40 % up)."""
    filter_ = vqf.VQF(0.02)
    drift = cd.CausalDrift(filter_)
    iron = np.array([150.0, -80.0, 300.0])
    rng = np.random.default_rng(2)
    for i, t in enumerate(np.arange(3.5, 23.5, 0.5)):
        angle = math.radians(angle_deg + rng.standard_normal())
        field = np.array([19.0 * math.sin(angle), 19.0 * math.cos(angle), -46.0])  # ENU, the body's axes
        if disturbed is not None and disturbed.start <= i < disturbed.stop:
            field = field + np.array([0.0, -25.0, -10.0])
        drift.note(float(t), field + iron, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
    return drift, iron


def _less(iron: np.ndarray) -> cd.Correct:
    """The correction of a record whose offset is ``iron`` (the raw field less it)."""

    def correct(raw: np.ndarray, gyr: np.ndarray) -> np.ndarray:
        return raw - iron

    return correct


def test_a_new_records_heading_comes_from_the_history_with_the_objects_left_out() -> None:
    for disturbed in (None, slice(34, 40)):  # the last 3 s beside an object: 6 of the last 12 rows
        drift, iron = _history(37.0, disturbed)
        filter_ = drift.filter
        correct = _less(iron)
        assert drift.heading_from_history(correct)
        assert abs(math.degrees(filter_.getDelta()) - 37.0) < 1.0
        state = filter_.state
        assert state["kMagInit"] == 0.0 and not state["magDistDetected"]
        assert abs(float(state["magRefNorm"]) - math.hypot(19.0, 46.0)) < 1.0
        assert abs(math.degrees(float(state["magRefDip"])) - math.degrees(math.atan2(46.0, 19.0))) < 1.0
        assert filter_.params["tauMag"] == cd.HEADING_WORTH_S  # vqf's average goes on, from the history's worth
        for t in (24.0, 24.0 + 9.0 - cd.HEADING_WORTH_S):
            drift.note(t, np.zeros(3) + 1.0, np.zeros(3))
        assert filter_.params["tauMag"] == 9.0 and drift.ramp is None


def test_no_heading_from_a_short_or_wholly_disturbed_history() -> None:
    drift, iron = _history(37.0)
    drift.history = drift.history[-4:]
    assert not drift.heading_from_history(lambda raw, gyr: raw - iron)
    assert drift.filter.state["kMagInit"] != 0.0  # vqf takes its first heading as it would
    drift, iron = _history(37.0, slice(28, 40))  # every row of the last 6 s beside the object
    assert not drift.heading_from_history(lambda raw, gyr: raw - iron)
