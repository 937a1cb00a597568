"""The dashboard's row carries the heading's one sigma the compass sent (``heading_sigma_deg``) for the dial, and
none from a compass that sends none."""

import dataclasses

import numpy as np
from test_dashboard_app import heading_batch

from magnet.earth.geomag import earth_field
from services.dashboard.state import FleetState


def _row(batch):
    state = FleetState(earth_field(50.45, 30.52, 0.0, "2025-06-01"))
    state.on_heading(batch)
    return state.rows["imu-1"].to_json(0.0, None)


def test_the_row_carries_the_last_samples_sigma():
    batch = dataclasses.replace(heading_batch(), heading_sigma_deg=np.array([3.0, 2.0, 1.0, 0.5, 0.75]))
    assert _row(batch)["heading_sigma_deg"] == 0.75


def test_a_compass_without_sigma_gives_none():
    assert _row(heading_batch())["heading_sigma_deg"] is None
