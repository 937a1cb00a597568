"""The sample CSV reader: numpy's C reader for tables of numbers, the csv module for the rest; both give the same
table (services.common.inputs.csvio)."""

from __future__ import annotations

import numpy as np

from services.common.inputs.csvio import parse_samples


def _text(rows: np.ndarray, header: str, extra: str = "") -> str:
    lines = [header + extra] + [",".join(repr(float(v)) for v in row) + ("," + "x" if extra else "") for row in rows]
    return "Fs,100\n" + "\n".join(lines) + "\n\n"


def test_numbers_and_a_table_with_a_text_column_read_the_same():
    rows = np.random.default_rng(1).normal(0.0, 30.0, (50, 7))
    fast = parse_samples(_text(rows, "t_s,mx,my,mz,ax,ay,az"))
    slow = parse_samples(_text(rows, "t_s,mx,my,mz,ax,ay,az", extra=",label"))  # a text column: the csv module
    assert isinstance(fast.columns["t_s"], np.ndarray) and isinstance(slow.columns["t_s"], list)
    np.testing.assert_array_equal(fast.mag, slow.mag)
    np.testing.assert_array_equal(fast.acc, slow.acc)
    np.testing.assert_array_equal(fast.numeric("t_s"), slow.numeric("t_s"))
    np.testing.assert_array_equal(fast.mag, rows[:, 1:4])


def test_velocity_before_the_first_fix_is_nan_in_both_readers():
    text = 't_s,mx,my,mz,vn,ve,vd\n0,1,2,3,nan,nan,nan\n0.1,1,2,3,"1.5",0,0\n'
    fast, slow = parse_samples(text), parse_samples(text.replace("nan,nan,nan", ",,"))  # empty cells: csv module
    np.testing.assert_array_equal(fast.vel_ned_ms(), [[np.nan] * 3, [1.5, 0.0, 0.0]])
    np.testing.assert_array_equal(slow.vel_ned_ms(), fast.vel_ned_ms())
