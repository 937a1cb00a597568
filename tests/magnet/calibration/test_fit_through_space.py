"""A field fit's samples come from a path through space, where the local field itself varies: its residual limits are
``TRAVEL_RESIDUAL_FACTOR`` times a tumble's (``magnet.quality.gate.for_travel``; docs/field-calibration.md, "The
field's own variation along a path")."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import fit_input_of

from magnet.calibration.choose import fit_choice
from magnet.quality import GateThresholds, for_travel, gate
from magnet.quality.gate import TRAVEL_RESIDUAL_FACTOR
from magnet.simulator import Disturbances, SensorErrors, SimulatorConfig, Trajectory, simulate

RATE_HZ = 50.0
#: a room's field: weak objects every 2-6 m, 1-2.5 m from the path, 2-8 uT at the closest (about 7 deg RMS of
#: heading and 2 uT RMS of |B| along a walk; BROAD's lab shows 3 % of |B| with a factory-calibrated sensor)
ROOM = Disturbances(every_m=(2.0, 6.0), first_m=(0.0, 2.0), door_share=0.0, car_m=(1.0, 2.5), car_ut=(2.0, 8.0))


def test_a_travelling_fit_is_gated_on_twice_the_residual_and_nothing_else_changes():
    base = GateThresholds(max_residual_ut=1.2, max_residual_pct=3.0, radius_tolerance_pct=10.0)
    travel = for_travel(base)
    assert travel.max_residual_ut == pytest.approx(1.2 * TRAVEL_RESIDUAL_FACTOR)
    assert travel.max_residual_pct == pytest.approx(3.0 * TRAVEL_RESIDUAL_FACTOR)
    assert travel.min_coverage == 0.0 and travel.max_scatter_condition == np.inf
    assert travel.radius_tolerance_pct == 10.0 and travel.max_dip_spread_deg == base.max_dip_spread_deg
    figures = {"residual_rms_ut": 2.0, "residual_rms_pct": 4.0, "coverage": 0.1}
    assert not gate(figures, base)[0] and gate(figures, travel)[0]
    assert not gate({**figures, "residual_rms_ut": 2.5}, travel)[0]  # the travelling limit is still a limit


def test_a_walk_through_a_room_whose_field_varies_gets_its_offset():
    """Two minutes of a texting walk through a room's field: the tumble's 1.6 uT refuses the offset (the room alone
    leaves about 2 uT); the travelling gate accepts it, within 4 uT of the hard iron (6-15 times the field)."""
    rng = np.random.default_rng([1, 26])
    errors = SensorErrors.phone(rng, 50.0)
    config = SimulatorConfig(
        trajectory=Trajectory.WALK_TEXTING, rate_hz=RATE_HZ, count=int(120 * RATE_HZ), errors=errors, seed=1,
        disturbances=ROOM,
    )  # fmt: skip
    run = simulate(config)
    data = fit_input_of(run, RATE_HZ)
    truth = errors.true_calibration(run.earth.total_ut)
    record = fit_choice(data, "auto")
    assert record.accepted, record.reason
    assert record.method == "offset"
    residual = float(record.quality.get("residual_rms_ut"))
    assert GateThresholds().max_residual_ut < residual < for_travel().max_residual_ut
    assert np.linalg.norm(record.offset - truth.offset) < 4.0
    assert np.linalg.norm(truth.offset) > 6 * run.earth.total_ut
