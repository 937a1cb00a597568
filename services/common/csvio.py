"""Reading sample CSVs for the offline commands, and writing CSV to a stream.

A sample CSV has a header row naming its columns; any lines before the header (a logger's preamble such as
``Fs,50.00``) are skipped: the header is the first line that names ``mx``, ``my`` and ``mz``. Columns are matched by
name, case-insensitively; unknown columns are ignored. Every problem is a ``ValueError`` that names the file, the
line and what to do.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TextIO

import numpy as np

MAG_COLUMNS = ("mx", "my", "mz")
ACC_COLUMNS = ("ax", "ay", "az")
MAX_PREAMBLE_LINES = 50


@dataclasses.dataclass(frozen=True)
class SampleTable:
    """Samples read from a CSV.

    mag: (N, 3) raw magnetometer readings in the file's unit. acc: (N, 3) accelerometer readings (any unit; only
    directions are used) or None when the file has no ``ax,ay,az``. columns: every other column by name, as strings.
    """

    path: str
    mag: np.ndarray
    acc: np.ndarray | None
    columns: dict[str, list[str]]

    def numeric(self, name: str) -> np.ndarray:
        """Column ``name`` as floats, shape (N,); ValueError naming the first bad row."""
        if name not in self.columns:
            raise ValueError(f"{self.path}: column {name!r} is missing (the header must name it)")
        return _floats(self.columns[name], name, self.path)

    def text(self, name: str) -> list[str]:
        if name not in self.columns:
            raise ValueError(f"{self.path}: column {name!r} is missing (the header must name it)")
        return [v.strip() for v in self.columns[name]]


def _floats(values: Sequence[str], name: str, path: str) -> np.ndarray:
    out = np.empty(len(values))
    for i, text in enumerate(values):
        try:
            out[i] = float(text)
        except ValueError:
            raise ValueError(f"{path}: row {i + 1}: {name}={text!r} is not a number") from None
        if not math.isfinite(out[i]):
            raise ValueError(f"{path}: row {i + 1}: {name}={text!r} is not finite")
    return out


def _find_header(lines: list[str], path: str) -> int:
    for index, line in enumerate(lines[:MAX_PREAMBLE_LINES]):
        names = {cell.strip().lower() for cell in line.split(",")}
        if set(MAG_COLUMNS) <= names:
            return index
    if not any(line.strip() for line in lines):
        raise ValueError(f"{path}: the file is empty: it needs a header row with mx,my,mz and samples below it")
    raise ValueError(
        f"{path}: no header row naming mx,my,mz in its first {MAX_PREAMBLE_LINES} lines "
        "(columns mx,my,mz are required; ax,ay,az optional)"
    )


def parse_samples(text: str, path: str = "<input>") -> SampleTable:
    """Parse CSV ``text`` into a SampleTable (see the module docstring for the format)."""
    lines = text.splitlines()
    header_index = _find_header(lines, path)
    reader = csv.reader(io.StringIO("\n".join(lines[header_index:])))
    header = [name.strip().lower() for name in next(reader)]
    rows = [row for row in reader if any(cell.strip() for cell in row)]
    if not rows:
        raise ValueError(f"{path}: the header is there but no samples follow it")
    for number, row in enumerate(rows, start=1):
        if len(row) < len(header):
            raise ValueError(f"{path}: row {number} has {len(row)} values but the header names {len(header)} columns")
    columns = {name: [row[i] for row in rows] for i, name in enumerate(header) if name}
    mag = np.column_stack([_floats(columns[c], c, path) for c in MAG_COLUMNS])
    acc = None
    if all(c in columns for c in ACC_COLUMNS):
        acc = np.column_stack([_floats(columns[c], c, path) for c in ACC_COLUMNS])
    return SampleTable(path=path, mag=mag, acc=acc, columns=columns)


def read_samples(path: str | Path) -> SampleTable:
    """Read a sample CSV file; ValueError for a file that is not one (OSError when it cannot be opened)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text CSV file") from None
    return parse_samples(text, str(path))


def write_csv(
    stream: TextIO, header: Sequence[str], columns: Iterable[np.ndarray], fmt: str | Sequence[str] = "%.6f"
) -> None:
    """Write equal-length columns under ``header`` as CSV rows (``fmt``: one printf format, or one per column)."""
    matrix = np.column_stack([np.asarray(c, dtype=float) for c in columns])
    stream.write(",".join(header) + "\n")
    np.savetxt(stream, matrix, delimiter=",", fmt=fmt)
