"""``magnet fit`` reads the velocity over the ground (``vn,ve,vd``): a car that drives straight, which the
magnetometer and gyroscope alone cannot calibrate, gets its offset from the velocity's heading and the WMM
(docs/field-calibration.md, "A vehicle that drives straight")."""

from __future__ import annotations

import argparse

import pytest

from services.bench import field, field_runs
from services.commands import fit as fit_command
from services.common.inputs import read_input
from services.common.inputs.input_options import InputOptions


def _fit(csv, *options: str):
    parser = argparse.ArgumentParser()
    fit_command.add_arguments(parser)
    args = parser.parse_args([str(csv), "--location", "50.45,30.52", "--date", "2026-01-01", *options])
    return fit_command.fit_table(read_input(csv, InputOptions.from_args(args)), args)


def test_magnet_fit_of_a_straight_driving_car_uses_its_velocity(tmp_path):
    run = field_runs.field_run(field_runs.MOTIONS["car"], 2026, field_runs.FieldSettings(seconds=20.0))
    with_velocity = field.write_run_csv(run, tmp_path / "car.csv", velocity=True)
    record = _fit(with_velocity)
    assert record.accepted and record.method == "offset"
    assert record.quality.get("heading_source") == "velocity over the ground"
    without = field.write_run_csv(run, tmp_path / "plain.csv")
    try:
        refused = _fit(without)
    except ValueError:  # nothing could be computed: as magnet fit says
        return
    assert not refused.accepted


def test_velocity_columns_must_come_together(tmp_path):
    csv = tmp_path / "bad.csv"
    rows = "".join(f"{0.02 * k:.2f},1,2,3,0,0,-9.8,0,0,0,1\n" for k in range(300))
    csv.write_text("t_s,mx,my,mz,ax,ay,az,gx,gy,gz,vn\n" + rows)
    with pytest.raises(ValueError, match="vn,ve,vd"):
        _fit(csv)
