"""The CSV writer: ``%.<d>f`` and ``%d`` columns written by the compiled ``magnet._kernels.format_rows`` give the
very characters Python's ``%`` gives (services.common.inputs.csvio.write_csv), ties and special values included."""

from __future__ import annotations

import io

import numpy as np
import pytest

from magnet import _kernels
from services.common.inputs.csvio import write_csv


def _values(n: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    return np.concatenate(
        [
            rng.normal(0.0, 1.0, n) * 10 ** rng.uniform(-8, 13, n),  # every magnitude the fast path takes, and beyond
            np.round(rng.normal(0.0, 1e4, n)) / 1e4 + 0.00005,  # near the ties of 4 decimals
            rng.integers(-(10**6), 10**6, n) / 2.0 ** rng.integers(0, 12, n),  # exact binary ties
            [np.nan, np.inf, -np.inf, -0.0, 0.0, 0.5, 1.5, 2.5, -2.5, 1e300, -1e-300, 0.125, 9.995, -9.995],
        ]
    )


@pytest.mark.parametrize("decimals", [0, 1, 3, 4, 6, 7, 9, 12, 20])
def test_format_rows_writes_what_python_writes(decimals):
    values = _values(5000)
    expected = "".join(f"%.{decimals}f\n" % x for x in values)
    assert _kernels.format_rows(values[:, None], bytes([decimals])).decode() == expected


def test_integer_columns_and_rows_of_many_columns():
    rng = np.random.default_rng(3)
    flags = rng.integers(-(1 << 40), 1 << 40, 500).astype(float)
    expected = "".join("%d\n" % x for x in flags)  # noqa: UP031 (Python's % is what is compared with)
    assert _kernels.format_rows(flags[:, None], bytes([255])).decode() == expected
    matrix = rng.normal(0.0, 50.0, (300, 3))
    matrix[:, 2] = np.round(matrix[:, 2])
    expected = "".join("%.4f,%.6f,%d\n" % tuple(row) for row in matrix)  # noqa: UP031
    assert _kernels.format_rows(matrix, bytes([4, 6, 255])).decode() == expected


def test_write_csv_gives_the_same_lines_through_either_path():
    rng = np.random.default_rng(5)
    columns = [rng.normal(0.0, 30.0, 9000), rng.integers(0, 64, 9000), rng.normal(0.0, 1.0, 9000)]
    fast, slow = io.StringIO(), io.StringIO()
    write_csv(fast, ["a", "flags", "b"], columns, ["%.4f", "%d", "%.7f"])
    write_csv(slow, ["a", "flags", "b"], columns, ["%.4f", "%i", "%.7f"])  # %i: not taken by the kernel
    assert fast.getvalue() == slow.getvalue()
    assert fast.getvalue().startswith("a,flags,b\n") and fast.getvalue().count("\n") == 9001


def test_bad_decimals_are_refused():
    with pytest.raises(ValueError, match="decimals"):
        _kernels.format_rows(np.zeros((2, 1)), bytes([21]))
    with pytest.raises(ValueError, match="float64"):
        _kernels.format_rows(np.zeros((2, 1), dtype=np.float32), bytes([2]))


@pytest.mark.parametrize(("encoding", "as_bytes"), [("utf-8", True), ("ascii", True), ("utf-16", False)])
def test_rows_go_below_a_text_stream_as_bytes_only_where_they_are_its_text(encoding, as_bytes):
    columns = [np.arange(5000) * 0.37, np.arange(5000) % 7]
    text = io.StringIO()
    write_csv(text, ["a", "b"], columns, fmt=["%.3f", "%d"])
    binary = io.BytesIO()
    stream = io.TextIOWrapper(binary, encoding=encoding)
    stream.write("# before\n")  # what the stream holds already goes first
    write_csv(stream, ["a", "b"], columns, fmt=["%.3f", "%d"])
    stream.flush()
    assert binary.getvalue().decode(encoding) == "# before\n" + text.getvalue()
    assert text.getvalue().count("\n") == 5001 and text.getvalue().endswith("1849.630,1\n")
    assert (binary.getvalue().count(b"\x00") == 0) == as_bytes
