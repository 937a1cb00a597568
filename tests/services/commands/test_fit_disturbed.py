"""``magnet fit`` leaves out the samples in a disturbed field unless ``--keep-disturbed`` (docs/field-calibration.md,
"Disturbed samples"): a walk past steel doors."""

from __future__ import annotations

import argparse

import numpy as np

from services.bench import field, field_runs
from services.commands import fit as fit_command
from services.common.inputs import read_input
from services.common.inputs.input_options import InputOptions


def _fit(csv, *options: str):
    parser = argparse.ArgumentParser()
    fit_command.add_arguments(parser)
    args = parser.parse_args([str(csv), "--location", "50.45,30.52", "--date", "2026-01-01", *options])
    table = read_input(csv, InputOptions.from_args(args))
    return fit_command.fit_input(table, args), fit_command.fit_table(table, args)


def test_magnet_fit_leaves_the_doors_out_unless_asked(tmp_path):
    settings = field_runs.FieldSettings(seconds=60.0)
    run = field_runs.field_run(field_runs.MOTIONS["walk-texting, doors"], 2026, settings)
    csv = field.write_run_csv(run, tmp_path / "doors.csv")
    truth = run.errors.true_calibration(run.earth.total_ut)
    data, record = _fit(csv)
    assert data.drop_disturbed and record.quality.get("disturbed_samples", 0) > 0
    kept_data, kept = _fit(csv, "--keep-disturbed")
    assert not kept_data.drop_disturbed and kept.quality.get("disturbed_samples") is None
    assert np.linalg.norm(record.offset - truth.offset) < np.linalg.norm(kept.offset - truth.offset)
