"""A refresh that hardly moves the field moves the causal filter's heading at once (``magnet.attitude.refresh_shift``):
a walk's compass with a record 3 uT off, then the right one, heads as one that had the right one all along, where
vqf's loop alone (tauMag) carried the old error on."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import wire
from magnet.attitude import refresh_shift
from magnet.compass import CompassCore, CoreSettings
from magnet.compass.calibrations import small_change
from magnet.earth.location import Location
from magnet.fleet.places import Places
from magnet.simulator import SensorErrors, SimulatorConfig, Trajectory, simulate
from services.bench import field_runs as fr

WALL_NS = 1_767_225_600_000_000_000
DEVICE, PREFIX, BATCH = "phone", "magnet", 25
FIRST_S, SWITCH_S = 10.0, 35.0


def _headings(run, records: list[tuple[float, bytes]]) -> np.ndarray:
    """The compass's heading error (deg, (N,)) on ``run`` with each record put in force at its time (s)."""
    location = Location.parse("50.45,30.52")
    compass = CompassCore(CoreSettings(drift=None, sigmas=False), Places(default=location, date="2026-01-01"))
    raw_key, cal_key = wire.key(PREFIX, DEVICE, wire.Kind.RAW), wire.key(PREFIX, DEVICE, wire.Kind.CALIBRATION)
    quat = np.full((len(run.t_s), 4), np.nan)
    pending = list(records)
    for seq, start in enumerate(range(0, len(run.t_s), BATCH)):
        part = slice(start, start + BATCH)
        while pending and pending[0][0] <= run.t_s[start]:
            assert compass.accept_calibration(pending.pop(0)[1], cal_key, PREFIX)
        t_ns = WALL_NS + np.round(run.t_s[part] * 1e9).astype(np.int64)
        batch = wire.RawBatch(
            DEVICE, seq, "sim", t_ns, run.mag_ut[part], run.acc_ms2[part], gyr_rads=run.gyr_rads[part]
        )
        out = compass.step(compass.decode([(raw_key, wire.encode_raw(batch))], PREFIX), int(t_ns[-1]))
        quat[part] = out.quat_wxyz
    return fr.heading_error_deg(quat, run.quat_wxyz)


@pytest.fixture(scope="module")
def walk():
    errors = SensorErrors.phone(np.random.default_rng([3, 26]), 50.0)
    config = SimulatorConfig(trajectory=Trajectory.WALK_TEXTING, count=2500, errors=errors, seed=3)
    run = simulate(config)
    right = errors.true_calibration(run.earth.total_ut)
    wrong = right.replace(offset=right.offset + np.array([2.0, -2.0, 1.0]))
    assert small_change(wrong, right)  # a refresh the filter keeps running through
    return run, wrong, right


def _after(run, error: np.ndarray) -> float:
    """Mean error (deg) over the 3 s after the switch."""
    return float(np.mean(error[(run.t_s >= SWITCH_S) & (run.t_s < SWITCH_S + 3.0)]))


def test_a_refresh_moves_the_heading_at_once(walk, monkeypatch):
    run, wrong, right = walk
    one = [(FIRST_S, wire.encode_calibration(DEVICE, right, WALL_NS))]
    two = [(FIRST_S, wire.encode_calibration(DEVICE, wrong, WALL_NS))]
    two.append((SWITCH_S, wire.encode_calibration(DEVICE, right, WALL_NS + 1)))
    always = _after(run, _headings(run, one))
    shifted = _after(run, _headings(run, two))
    monkeypatch.setattr(refresh_shift, "ENABLED", False)
    loop_only = _after(run, _headings(run, two))
    assert abs(shifted - always) < 0.5, (shifted, always)
    assert abs(loop_only - always) > 1.5, (loop_only, always)
