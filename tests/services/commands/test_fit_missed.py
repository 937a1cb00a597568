"""``magnet fit`` on a file that dropped samples (docs/field-calibration.md, "Samples dropped"): the rate after k
missing samples is taken over their k + 1 periods; a file without gaps is read as it is."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from services.bench import field, field_runs
from services.commands import fit as fit_command
from services.common.inputs import read_input
from services.common.inputs.csvio import gyro_columns
from services.common.inputs.input_options import InputOptions


def _input(csv):
    parser = argparse.ArgumentParser()
    fit_command.add_arguments(parser)
    args = parser.parse_args([str(csv), "--location", "50.45,30.52", "--date", "2026-01-01"])
    return fit_command.fit_input(read_input(csv, InputOptions.from_args(args)), args)


def test_the_rate_after_missing_samples_spans_them_and_a_whole_file_is_as_it_was(tmp_path):
    settings = field_runs.FieldSettings(seconds=20.0)
    run = field_runs.field_run(field_runs.MOTIONS["walk-hand"], 1, settings)
    whole = _input(field.write_run_csv(run, tmp_path / "whole.csv"))
    csv = field.write_run_csv(run, tmp_path / "whole.csv")
    np.testing.assert_array_equal(whole.gyr_rads, gyro_columns(read_input(csv, InputOptions())))  # to the bit
    n = len(run.t_s)
    keep = np.ones(n, dtype=bool)
    keep[[100, 300, 301, 500, 501, 502, 700, 701, 702, 703, 704]] = False  # 1, 2, 3 missing, then a stall of 5
    cut = dataclasses.replace(
        run,
        **{
            f.name: getattr(run, f.name)[keep]
            for f in dataclasses.fields(run)
            if isinstance(getattr(run, f.name), np.ndarray) and getattr(run, f.name).shape[:1] == (n,)
        },
    )
    dropped = _input(field.write_run_csv(cut, tmp_path / "dropped.csv"))
    times = np.ones(len(cut.t_s))
    after = np.flatnonzero(np.diff(np.flatnonzero(keep)) > 1) + 1
    times[after] = [2.0, 3.0, 4.0, 4.0]  # a stall's rotation is made up for 3 samples at most
    np.testing.assert_allclose(dropped.gyr_rads, cut.gyr_rads * times[:, None], atol=1e-8)
