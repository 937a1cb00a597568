"""Drift alerts (magnet.drift): no false alarm on a still device over a long noisy run with trucks and motor bursts,
a sustained change raises an alert within the stated bound and recovery clears it, a simulated iron change on a
tumbling device is caught and a recalibration clears it."""

from __future__ import annotations

import numpy as np
import pytest

from magnet.attitude import heading as hd
from magnet.calibration import FitInput, fit
from magnet.drift import NS_PER_DAY, NS_PER_S, AlertKind, DriftMonitor, DriftSettings, DriftTracker, Reference
from magnet.simulator import SimulatedDevices

RATE_HZ = 10.0
REF_UT, DIP_DEG = 50.0, 67.0


def still_run(seconds: float, rng: np.random.Generator, *, noise_ut: float = 0.3, start_s: float = 0.0):
    """t_ns, |B| (uT) and dip (deg) of a still device at RATE_HZ: |B| noisy around REF_UT, dip around DIP_DEG."""
    t_s = start_s + np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    strength = REF_UT + noise_ut * rng.standard_normal(t_s.size)
    dip = DIP_DEG + np.degrees(noise_ut / REF_UT) * rng.standard_normal(t_s.size)
    return (t_s * NS_PER_S).astype(np.int64), strength, dip


def feed(tracker: DriftTracker, t_ns, strength, dip, chunk: int = 500):
    """Everything in batches of ``chunk`` samples (as raw batches arrive); the alert events."""
    events = []
    for lo in range(0, t_ns.size, chunk):
        events += tracker.add(t_ns[lo : lo + chunk], strength[lo : lo + chunk], dip[lo : lo + chunk])
    return events


def test_a_still_device_raises_nothing_over_a_day_of_noise_trucks_and_motor_bursts():
    rng = np.random.default_rng(7)
    t_ns, strength, dip = still_run(24 * 3600, rng)
    t_s = t_ns / NS_PER_S
    truck = (t_s % 900.0) < 20.0  # a truck parks by for 20 s every quarter of an hour: +12 uT, +8 deg
    burst = (t_s % 120.0) < 3.0  # a motor burst of 3 s every 2 minutes: +30 uT, -15 deg
    strength = strength + 12.0 * truck + 30.0 * burst
    dip = dip + 8.0 * truck - 15.0 * burst
    tracker = DriftTracker(
        "still", Reference(REF_UT, residual_ut=0.5, model_total_ut=REF_UT + 1.0, model_dip_deg=DIP_DEG - 0.5)
    )
    events = feed(tracker, t_ns, strength, dip, chunk=5000)
    assert events == []
    assert tracker.windows_judged >= 24 * 3600 / 30 - 2


@pytest.mark.parametrize("kind, shift", [(AlertKind.FIELD_STRENGTH, (6.0, 0.0)), (AlertKind.DIP, (0.0, 7.0))])
def test_a_sustained_departure_alerts_within_the_bound_and_clears_when_it_recovers(kind, shift):
    settings = DriftSettings()
    rng = np.random.default_rng(3)
    t_ns, strength, dip = still_run(3600, rng)
    change_s, recover_s = 1000.3, 2000.7
    t_s = t_ns / NS_PER_S
    changed = (t_s >= change_s) & (t_s < recover_s)
    strength, dip = strength + shift[0] * changed, dip + shift[1] * changed
    tracker = DriftTracker("d", Reference(REF_UT, residual_ut=0.5))
    events = []
    raised_at = cleared_at = None
    for lo in range(0, t_ns.size, 50):
        new = tracker.add(t_ns[lo : lo + 50], strength[lo : lo + 50], dip[lo : lo + 50])
        for event in new:
            if event.cleared:
                cleared_at = cleared_at or t_s[lo + 49]
            else:
                raised_at = raised_at or t_s[lo + 49]
        events += new
    assert [(e.kind, e.cleared) for e in events] == [(kind, False), (kind, True)]
    assert change_s < raised_at <= change_s + settings.detection_bound_s
    assert recover_s < cleared_at <= recover_s + settings.detection_bound_s
    raised = events[0]
    assert abs(raised.since_ns / NS_PER_S - change_s) <= settings.window_s
    expected = REF_UT if kind is AlertKind.FIELD_STRENGTH else DIP_DEG
    assert raised.expected == pytest.approx(expected, abs=0.5)
    assert raised.measured - raised.expected == pytest.approx(max(shift), abs=0.5)
    message = raised.to_message()
    assert set(message) == {"v", "device", "kind", "since_ns", "measured", "expected", "advice"}
    assert message["v"] == 1 and message["kind"] == kind.value and "recalibrate" in message["advice"]
    assert events[1].to_message()["cleared"] is True


def test_the_model_catches_a_field_far_from_the_worlds_even_when_the_calibration_agrees():
    rng = np.random.default_rng(4)
    t_ns, strength, dip = still_run(600, rng)
    tracker = DriftTracker("wrong-place", Reference(REF_UT, residual_ut=0.5, model_total_ut=REF_UT + 25.0))
    events = feed(tracker, t_ns, strength, dip)
    assert [e.kind for e in events] == [AlertKind.FIELD_STRENGTH]
    assert events[0].expected == pytest.approx(REF_UT + 25.0)
    assert events[0].measured == pytest.approx(REF_UT, abs=0.2)


def test_an_old_calibration_raises_calibration_age_once():
    rng = np.random.default_rng(5)
    t_ns, strength, dip = still_run(300, rng)
    created = int(t_ns[0]) - 400 * NS_PER_DAY
    tracker = DriftTracker("old", Reference(REF_UT, created_ns=created))
    events = feed(tracker, t_ns, strength, dip)
    assert [e.kind for e in events] == [AlertKind.CALIBRATION_AGE]
    assert events[0].measured == pytest.approx(400, abs=0.1) and events[0].expected == 365
    assert events[0].since_ns == created + 365 * NS_PER_DAY


@pytest.mark.parametrize(
    "bad",
    [
        {"window_s": 0},
        {"raise_windows": 1.5},
        {"clear_fraction": 1.2},
        {"strength_tol_pct": float("nan")},
        {"max_age_days": -1},
    ],
)
def test_drift_settings_refuse_nonsense(bad):
    with pytest.raises(ValueError):
        DriftSettings(**bad)


def calibrated(cal, mag, acc):
    field = cal.apply(mag)
    return np.linalg.norm(field, axis=1), hd.dip_angle_deg(field, acc)


def test_a_simulated_iron_change_on_a_tumbling_device_alerts_in_time_and_a_recalibration_clears_it():
    settings = DriftSettings()
    sim = SimulatedDevices(1, rate_hz=RATE_HZ, seed=11, noise_ut=0.3)

    def run(seconds):
        batch = sim.step(int(seconds * RATE_HZ))
        return batch.t_ns, batch.mag_ut[0], batch.acc_ms2[0]

    t0, mag0, acc0 = run(180)
    cal = fit(FitInput(mag0, acc=acc0, field_ut=sim.earth.total_ut), "ellipsoid")
    assert cal.accepted, cal.reason
    monitor = DriftMonitor(settings)
    reference = Reference(
        cal.field_strength,
        cal.quality.residual_rms_ut or 0.0,
        sim.earth.total_ut,
        sim.earth.inclination_deg,
        int(t0[0]),
        cal.content_id,
    )
    monitor.calibration("car-1", reference, int(t0[0]))
    t1, mag1, acc1 = run(900)
    assert monitor.add("car-1", t1, *calibrated(cal, mag1, acc1)) == []  # 15 min unchanged: nothing
    change_ns = int(t1[-1]) + int(NS_PER_S / RATE_HZ)
    sim.change_iron(0, hard_iron_ut=sim.errors[0].hard_iron_ut + np.array([9.0, -6.0, 4.0]))
    events, alert_ns = [], None
    for _ in range(int(2 * settings.detection_bound_s / 10)):
        t, mag, acc = run(10)
        new = monitor.add("car-1", t, *calibrated(cal, mag, acc))
        if new and alert_ns is None:
            alert_ns = int(t[-1])
        events += new
    assert events and not any(e.cleared for e in events), events
    assert alert_ns - change_ns <= settings.detection_bound_s * NS_PER_S
    t2, mag2, acc2 = run(180)  # recalibrate with the new iron
    recal = fit(FitInput(mag2, acc=acc2, field_ut=sim.earth.total_ut), "ellipsoid")
    assert recal.accepted, recal.reason
    cleared = monitor.calibration(
        "car-1",
        Reference(
            recal.field_strength,
            recal.quality.residual_rms_ut or 0.0,
            sim.earth.total_ut,
            sim.earth.inclination_deg,
            int(t2[-1]),
            recal.content_id,
        ),
        int(t2[-1]),
    )
    assert {e.kind for e in cleared} == {e.kind for e in events} and all(e.cleared for e in cleared)
    t3, mag3, acc3 = run(900)
    assert monitor.add("car-1", t3, *calibrated(recal, mag3, acc3)) == []
    assert monitor.open_alerts() == []
