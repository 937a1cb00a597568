"""The sample CSV reader: numpy's C reader for tables of numbers, the csv module for the rest; both give the same
table (services.common.inputs.csvio)."""

from __future__ import annotations

import numpy as np
import pytest

from magnet import _kernels
from services.common.inputs import csvio
from services.common.inputs.csvio import parse_samples


def _text(rows: np.ndarray, header: str, extra: str = "") -> str:
    lines = [header + extra] + [",".join(repr(float(v)) for v in row) + ("," + "x" if extra else "") for row in rows]
    return "Fs,100\n" + "\n".join(lines) + "\n\n"


def test_numbers_and_a_table_with_a_text_column_read_the_same():
    rows = np.random.default_rng(1).normal(0.0, 30.0, (50, 7))
    fast = parse_samples(_text(rows, "t_s,mx,my,mz,ax,ay,az"))
    slow = parse_samples(_text(rows, "t_s,mx,my,mz,ax,ay,az", extra=",label"))  # a text column: the csv module
    assert isinstance(fast.columns["t_s"], np.ndarray) and isinstance(slow.columns["t_s"], np.ndarray)
    assert slow.columns["label"] == ["x"] * 50  # a column of numbers is kept as floats, one of text as strings
    np.testing.assert_array_equal(fast.mag, slow.mag)
    np.testing.assert_array_equal(fast.acc, slow.acc)
    np.testing.assert_array_equal(fast.numeric("t_s"), slow.numeric("t_s"))
    np.testing.assert_array_equal(fast.mag, rows[:, 1:4])


def test_velocity_before_the_first_fix_is_nan_in_both_readers():
    text = 't_s,mx,my,mz,vn,ve,vd\n0,1,2,3,nan,nan,nan\n0.1,1,2,3,"1.5",0,0\n'
    fast, slow = parse_samples(text), parse_samples(text.replace("nan,nan,nan", ",,"))  # empty cells: csv module
    np.testing.assert_array_equal(fast.vel_ned_ms(), [[np.nan] * 3, [1.5, 0.0, 0.0]])
    np.testing.assert_array_equal(slow.vel_ned_ms(), fast.vel_ned_ms())


def test_column_checks_are_the_numpy_reductions_they_replace():
    """``column_checks`` (the CSV reader's one pass over a table) against the plain numpy: per column the widest
    finite |x|, how many NaN, how many infinite; C-ordered, Fortran-ordered and strided tables."""
    rng = np.random.default_rng(11)
    for rows, cols in [(0, 3), (1, 1), (7, 4), (2000, 13)]:
        table = rng.normal(0.0, 1.0, (rows, cols)) * 10 ** rng.uniform(-5, 12, (rows, cols))
        mask = rng.random((rows, cols))
        table[mask < 0.01] = np.nan
        table[(mask >= 0.01) & (mask < 0.015)] = np.inf
        table[(mask >= 0.015) & (mask < 0.02)] = -np.inf
        for view in (table, np.asfortranarray(table), np.repeat(table, 2, axis=1)[:, ::2]):
            out = np.full((cols, 3), -1.0)
            _kernels.column_checks(view, out)
            finite = np.isfinite(view)
            widest = np.where(finite, np.abs(view), 0.0).max(axis=0, initial=0.0)
            np.testing.assert_array_equal(out[:, 0], widest)
            np.testing.assert_array_equal(out[:, 1], np.isnan(view).sum(axis=0))
            np.testing.assert_array_equal(out[:, 2], np.isinf(view).sum(axis=0))
    with pytest.raises(ValueError, match="out"):
        _kernels.column_checks(np.zeros((4, 2)), np.zeros((3, 3)))


def test_rows_read_by_the_csv_module_are_not_kept_and_blank_ones_cost_nothing():
    """Issue 32's front door for CSV: 10 million rows of empty cells (30 MB) peaked at 900 MB (the text split into a
    list of every line, joined again, then every row kept). Now the lines are split a block at a time and each cell
    goes into its column as it is read: 300,000 blank rows trace under 3 MB besides the text."""
    import tracemalloc

    text = "mx,my,mz\n" + ",,\n" * 300_000
    tracemalloc.start()
    with pytest.raises(ValueError, match="the header is there but no samples follow it"):
        parse_samples(text, "blank.csv")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 3_000_000, peak


def test_a_bad_cell_keeps_its_column_as_text_and_is_named_and_the_cells_are_bounded(monkeypatch):
    text = "mx,my,mz,t_s\n1,2,3,0\n1,2,3,0.1\n4,5,6,\n"
    table = parse_samples(text, "bad.csv")
    assert isinstance(table.columns["mx"], np.ndarray) and table.columns["t_s"] == ["0", "0.1", ""]
    with pytest.raises(ValueError, match="row 3: t_s='' is not a number"):
        table.numeric("t_s")
    with pytest.raises(ValueError, match="row 2: mz='x' is not a number"):
        parse_samples(text.replace("3,0.1", "x,0.1"), "bad.csv")
    with pytest.raises(ValueError, match="row 2 has 2 values but the header names 3 columns"):
        parse_samples("mx,my,mz\n1,2,3\n1,2\n,,\nx,1,2\n", "short.csv")
    monkeypatch.setattr(csvio, "MAX_TEXT_CELLS", 8)
    with pytest.raises(ValueError, match="more than 8 cells that are not all numbers"):
        parse_samples(text, "bad.csv")


def test_a_line_over_a_mib_is_refused_before_numpy_or_the_csv_module_takes_it(tmp_path):
    """A 64 MB line of digits (a field over 128 KiB either way) peaked at 485-550 MB: numpy's reader and the line
    splitting copied it several times before the csv module's field limit. Now the scan of the file and the line
    splitting refuse a line over ``MAX_LINE_CHARS`` (1 MiB), naming it."""
    import tracemalloc

    path = tmp_path / "long.csv"
    path.write_text("mx,my,mz\n1,2,3\n" + "1" * (8 << 20) + "\n")
    tracemalloc.start()
    with pytest.raises(ValueError, match=r"long.csv: line 3 is longer than 1 MiB: not a sample CSV"):
        csvio.read_samples(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert peak < 3.5 * (8 << 20), peak  # the bytes read and the text: not the line copied again
