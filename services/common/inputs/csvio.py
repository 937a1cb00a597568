"""Reading sample CSVs for the offline commands, and writing CSV to a stream.

A sample CSV has a header row naming its columns; any lines before the header (a logger's preamble such as
``Fs,50.00``) are skipped: the header is the first line that names ``mx``, ``my`` and ``mz``. Columns are matched by
name, case-insensitively; unknown columns are ignored, a column the commands read may not be named twice. Cells may
be quoted (``"mx","my","mz"``); values are separated by commas: a file separated otherwise (semicolons, tabs) is
refused with the separator named. A file over ``MAX_CSV_BYTES`` or not UTF-8 is refused, a field over 128 KiB or a
line over ``MAX_LINE_CHARS`` too, and so is a sensor reading (``mx..mz``, ``ax..az``, ``gx..gz``) beyond +-1e9 in
any unit. Values not all numbers: the csv module, no row kept. Every problem is a ``ValueError`` naming the file.
"""

from __future__ import annotations

import codecs
import csv
import dataclasses
import itertools
import math
import os
import re
import stat
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import BinaryIO, TextIO

import numpy as np

from magnet import _kernels

MAG_COLUMNS = ("mx", "my", "mz")
ACC_COLUMNS = ("ax", "ay", "az")
GYRO_COLUMNS = ("gx", "gy", "gz")
MAX_PREAMBLE_LINES = 50
#: no sensor reads beyond this in any unit (nT, counts, m/s^2, rad/s): such a value is a wrong column or a broken file
MAX_READING = 1e9
#: the largest sample file read (the file is held in memory as text and rows): an hour at 1 kHz of a dozen columns
#: is about 200 MB
MAX_CSV_BYTES = 512 * 1024 * 1024
#: the csv module's own limit on one field (128 KiB)
MAX_FIELD_CHARS = csv.field_size_limit()
#: rows formatted at once by ``write_csv``
WRITE_ROWS = 4096
#: the bytes searched for the header by ``read_samples`` before the whole file is decoded (``_file_table``)
HEAD_CHARS = 1 << 16
#: the bytes ``_file_table`` checks at a time
SCAN_BYTES = 1 << 18
#: the characters of text split into lines at a time (``_lines``)
LINE_BLOCK_CHARS = 1 << 16
#: the longest line read (a line of a sample CSV is a few hundred characters; each cell at most ``MAX_FIELD_CHARS``)
MAX_LINE_CHARS = 1 << 20
#: the most cells the csv module's reader takes (about 75 bytes each until read whole; 50 Hz, 11 columns, an hour)
MAX_TEXT_CELLS = 2_000_000
TEXT_CELLS = "empty cells, text or a bad value; write missing values as nan, or split the recording"
#: the ASCII line breaks of ``str.splitlines`` that a file read as text (universal newlines) does not break at
OTHER_LINE_BREAKS = (b"\x0b", b"\x0c", b"\x1c", b"\x1d", b"\x1e")
#: other separators named when the header is found with one of them
OTHER_SEPARATORS = {";": "semicolons", "\t": "tabs", "|": "'|'", " ": "spaces"}


@dataclasses.dataclass(frozen=True)
class SampleTable:
    """Samples read from a CSV.

    mag: (N, 3) raw magnetometer readings in the file's unit. acc: (N, 3) accelerometer readings (any unit; only
    directions are used) or None when the file has no ``ax,ay,az``. columns: every other column by name, as strings
    (from a CSV) or as float arrays (N,) (from a recording that holds numbers, see ``services.common.inputs``).
    note: what a reader wants the user told about where the samples came from ("" for a CSV)."""

    path: str
    mag: np.ndarray
    acc: np.ndarray | None
    columns: dict[str, list[str] | np.ndarray]
    duplicated: frozenset[str] = frozenset()  # names the header gives more than once: refused when read
    note: str = ""

    def _column(self, name: str) -> list[str] | np.ndarray:
        if name in self.duplicated:
            raise ValueError(f"{self.path}: the header names column {name!r} more than once: keep one of them")
        if name not in self.columns:
            raise ValueError(f"{self.path}: column {name!r} is missing (the header must name it)")
        return self.columns[name]

    def numeric(self, name: str, missing_ok: bool = False) -> np.ndarray:
        """Column ``name`` as floats, shape (N,); ValueError naming the first bad row. ``missing_ok``: empty and
        ``nan`` cells are NaN (a value not known at that sample)."""
        column = self._column(name)
        if isinstance(column, np.ndarray):
            return column.astype(np.float64)
        if missing_ok:
            column = ["nan" if str(v).strip() in ("", "nan") else v for v in column]
            known = [i for i, v in enumerate(column) if v != "nan"]
            out = np.full(len(column), np.nan)
            out[known] = _floats([column[i] for i in known], name, self.path)
            return out
        return _floats(column, name, self.path)

    def vel_ned_ms(self) -> np.ndarray | None:
        """The velocity columns ``vn,ve,vd`` (N, 3) m/s NED, NaN rows where empty or ``nan`` (no fix yet), or None
        when the file has none of them; ValueError when it has only some."""
        present = [c for c in VELOCITY_COLUMNS if c in self.columns]
        if not present:
            return None
        if len(present) < 3:
            raise ValueError(f"{self.path}: velocity needs all of vn,ve,vd (m/s north, east, down), found {present}")
        return np.column_stack([self.numeric(c, missing_ok=True) for c in VELOCITY_COLUMNS])

    def text(self, name: str) -> list[str]:
        return [str(v).strip() for v in self._column(name)]


#: velocity over the ground, m/s north, east, down
VELOCITY_COLUMNS = ("vn", "ve", "vd")


def _floats(values: Sequence[str], name: str, path: str) -> np.ndarray:
    """Floats of one column (N,); ValueError naming the row of a value that is not a finite number, or of a sensor
    reading beyond +-MAX_READING."""
    limit = MAX_READING if name in (*MAG_COLUMNS, *ACC_COLUMNS, *GYRO_COLUMNS) else math.inf
    out = np.empty(len(values))
    for i, text in enumerate(values):
        try:
            out[i] = float(text)
        except ValueError:
            raise ValueError(f"{path}: row {i + 1}: {name}={text!r} is not a number") from None
        if not math.isfinite(out[i]):
            raise ValueError(f"{path}: row {i + 1}: {name}={text!r} is not finite")
        if abs(out[i]) > limit:
            raise ValueError(
                f"{path}: row {i + 1}: {name}={text!r} is beyond +-{limit:.0e}: no sensor reads that in any "
                "unit (a wrong column, or a damaged file)"
            )
    return out


def _cells(line: str, path: str, number: int, delimiter: str = ",") -> list[str]:
    """The cells of one line (quotes removed), lower case; ValueError for a field over 128 KiB."""
    try:
        return [cell.strip().lower() for cell in next(csv.reader([line], delimiter=delimiter), [])]
    except csv.Error as exc:
        raise ValueError(f"{path}: line {number}: {_csv_problem(exc)}") from None


def _csv_problem(exc: csv.Error) -> str:
    if "field larger" in str(exc):
        return f"a field longer than {MAX_FIELD_CHARS // 1024} KiB: not a sample CSV"
    return f"not CSV ({exc})"


def _lines(text: str, path: str) -> Iterator[str]:
    """``text.splitlines()``, ``LINE_BLOCK_CHARS`` at a time (no list of every line); ValueError naming a line over
    ``MAX_LINE_CHARS``."""
    start, end, count = 0, len(text), 0
    while start < end:
        stop = text.find("\n", start + LINE_BLOCK_CHARS)
        stop = end if stop < 0 else stop + 1  # cut after a line feed: a line's end wherever it is
        if stop - start > LINE_BLOCK_CHARS + MAX_LINE_CHARS:
            before = text.rfind("\n", start, start + LINE_BLOCK_CHARS)
            count += len(text[start : before + 1].splitlines()) if before >= 0 else 0
            raise ValueError(f"{path}: line {count + 1} is longer than {MAX_LINE_CHARS // 2**20} MiB: not a sample CSV")
        block = text[start:stop].splitlines()
        count += len(block)
        yield from block
        start = stop


def _find_header(lines: list[str], path: str, blank: bool) -> int:
    """The index of the header among ``lines`` (the file's first); ``blank``: the whole file is blank."""
    for index, line in enumerate(lines[:MAX_PREAMBLE_LINES]):
        if set(MAG_COLUMNS) <= set(_cells(line, path, index + 1)):
            return index
    if blank:
        raise ValueError(f"{path}: the file is empty: it needs a header row with mx,my,mz and samples below it")
    for index, line in enumerate(lines[:MAX_PREAMBLE_LINES]):
        for separator, words in OTHER_SEPARATORS.items():
            if set(MAG_COLUMNS) <= set(_cells(line, path, index + 1, separator)):
                raise ValueError(
                    f"{path}: line {index + 1} names mx,my,mz separated by {words}, not commas: save the file as "
                    "comma-separated values (with decimal points)"
                )
    raise ValueError(
        f"{path}: no header row naming mx,my,mz in its first {MAX_PREAMBLE_LINES} lines "
        "(columns mx,my,mz are required; ax,ay,az optional)"
    )


def parse_samples(text: str, path: str = "<input>") -> SampleTable:
    """Parse CSV ``text`` into a SampleTable (see the module docstring for the format). A table of numbers is read
    by numpy's C reader (``_numbers``); anything else (text columns, empty cells, a row of another length, a value
    that is refused) by the csv module, cell by cell, which names the line or row and the value at fault."""
    lines = list(itertools.islice(_lines(text, path), MAX_PREAMBLE_LINES))
    header_index = _find_header(lines, path, not text or text.isspace())
    table = _numbers(lines[header_index], itertools.islice(_lines(text, path), header_index + 1, None), path)
    if table is not None:
        return table
    header, columns = _read_columns(text, header_index, path)
    duplicated = frozenset(name for name in columns if header.count(name) > 1)
    table = SampleTable(path, np.empty((0, 3)), None, columns, duplicated)
    mag = np.column_stack([table.numeric(c) for c in MAG_COLUMNS])
    acc = None
    if all(c in columns for c in ACC_COLUMNS):
        acc = np.column_stack([table.numeric(c) for c in ACC_COLUMNS])
    return dataclasses.replace(table, mag=mag, acc=acc)


def _file_table(handle: BinaryIO, path: Path) -> SampleTable | None:
    """The table of numbers (``_numbers``) of a regular file open in ``handle`` (at its start), in ASCII, whose lines
    break only where a file read as text does, none over ``MAX_LINE_CHARS``, not over ``MAX_CSV_BYTES``, its header
    among its first ``HEAD_CHARS`` bytes, read by numpy from the file itself (no Python string of the text or of each
    line); else None. The checks read ``SCAN_BYTES`` at a time into one buffer."""
    head = handle.read(HEAD_CHARS)
    size, buffer = len(head), bytearray(SCAN_BYTES)
    chunk: bytes | bytearray = head
    run = 0  # characters since the last line feed
    while chunk:
        if not chunk.isascii() or any(c in chunk for c in OTHER_LINE_BREAKS) or size > MAX_CSV_BYTES:
            return None
        first, last = chunk.find(b"\n"), chunk.rfind(b"\n")
        if run + (first if first >= 0 else len(chunk)) > MAX_LINE_CHARS:
            return None  # a line too long for numpy's reader to be handed (the csv module's path names it)
        run = len(chunk) - last - 1 if last >= 0 else run + len(chunk)
        count = handle.readinto(buffer)  # type: ignore[attr-defined]
        size += count
        chunk = buffer if count == len(buffer) else bytes(buffer[:count])
    lines = head.decode("ascii").splitlines()[: MAX_PREAMBLE_LINES + 1]
    if size > HEAD_CHARS:
        lines = lines[:-1]  # the last may be cut
    for index, line in enumerate(lines[:MAX_PREAMBLE_LINES]):
        if set(MAG_COLUMNS) <= set(_cells(line, str(path), index + 1)):
            return _numbers(line, path, str(path), skip=index + 1)
    return None


def _numbers(header_line: str, rows: Iterable[str] | Path, path: str, skip: int = 0) -> SampleTable | None:
    """The table when every row below the header is as many finite numbers as the header names columns (``nan``
    allowed in ``vn,ve,vd``: no fix yet), no column is named twice and no sensor reading is beyond +-MAX_READING,
    read by numpy's C reader (``numpy.loadtxt``) from ``rows``: the lines below the header, or a file whose first
    ``skip`` lines end with the header (ASCII, checked before); else None, and the csv module reads the file and
    says what is wrong with it."""
    header = _cells(header_line, path, 1)
    if len(set(header)) < len(header):
        return None
    try:
        with warnings.catch_warnings():  # blank lines alone: "input contained no data", the csv module says so
            warnings.simplefilter("ignore", UserWarning)
            values = np.loadtxt(
                rows, delimiter=",", quotechar='"', comments=None, ndmin=2, skiprows=skip, encoding="utf-8"
            )
    except ValueError:
        return None
    if values.shape != (values.shape[0], len(header)) or values.shape[0] == 0:
        return None
    sensors = [i for i, name in enumerate(header) if name in (*MAG_COLUMNS, *ACC_COLUMNS, *GYRO_COLUMNS)]
    others = [i for i, name in enumerate(header) if name not in VELOCITY_COLUMNS]  # NaN in vn,ve,vd: no fix yet
    checks = np.empty((len(header), 3))  # per column: the widest finite |x|, how many NaN, how many infinite
    _kernels.column_checks(values, checks)  # one pass over the table (three numpy reductions along its short axis)
    if checks[:, 2].any() or checks[others, 1].any() or (checks[sensors, 0] > MAX_READING).any():
        return None
    columns: dict[str, list[str] | np.ndarray] = {name: values[:, i] for i, name in enumerate(header) if name}
    # (N, 3) copies by ``take``: C-contiguous, a fifth of the time of fancy indexing's
    acc = values.take([header.index(c) for c in ACC_COLUMNS], axis=1) if set(ACC_COLUMNS) <= set(header) else None
    mag = values.take([header.index(c) for c in MAG_COLUMNS], axis=1)
    return SampleTable(path, mag, acc, columns)


def _read_columns(text: str, header_index: int, path: str) -> tuple[list[str], dict[str, list[str] | np.ndarray]]:
    """(header names in lower case, the named columns of the non-blank rows below it: ``_as_floats``); ValueError
    naming the line of a field over 128 KiB or not CSV, when no row follows the header, the first row shorter than
    the header, or past ``MAX_TEXT_CELLS`` cells. No row is kept: each cell goes into its column as it is read."""
    reader = csv.reader(line + "\n" for line in itertools.islice(_lines(text, path), header_index, None))
    try:
        header = [name.strip().lower() for name in next(reader)]
        named = {name: i for i, name in enumerate(header) if name}  # a name given twice: its last column
        cells: dict[str, list[str]] = {name: [] for name in named}
        count, short = 0, None
        for row in reader:
            if not "".join(row).strip():  # blank: no cell but spaces
                continue
            count += 1
            if len(row) < len(header):
                short = short or (count, len(row))
                continue
            for name, i in named.items():
                cells[name].append(row[i])
            if count * len(named) > MAX_TEXT_CELLS:
                raise ValueError(f"{path}: more than {MAX_TEXT_CELLS} cells that are not all numbers: {TEXT_CELLS}")
    except csv.Error as exc:
        raise ValueError(f"{path}: line {header_index + reader.line_num}: {_csv_problem(exc)}") from None
    if not count:
        raise ValueError(f"{path}: the header is there but no samples follow it")
    if short is not None:
        raise ValueError(f"{path}: row {short[0]} has {short[1]} values but the header names {len(header)} columns")
    return header, {name: _as_floats(name, values) for name, values in cells.items()}


def _as_floats(name: str, cells: list[str]) -> list[str] | np.ndarray:
    """``cells`` as floats when all are finite numbers (sensors within +-MAX_READING), else as they are."""
    try:
        values = np.fromiter(map(float, cells), float, len(cells))
    except ValueError:
        return cells
    limit = MAX_READING if name in (*MAG_COLUMNS, *ACC_COLUMNS, *GYRO_COLUMNS) else math.inf
    return values if np.isfinite(values).all() and not (np.abs(values) > limit).any() else cells


def read_samples(path: str | Path) -> SampleTable:
    """Read a sample CSV file; ValueError for a file that is not one (OSError when it cannot be opened)."""
    path = Path(path)
    with open(path, "rb") as handle:
        if stat.S_ISREG(os.fstat(handle.fileno()).st_mode):  # read twice: not a pipe
            table = _file_table(handle, path)
            if table is not None:
                return table
            handle.seek(0)
        data = bytearray()  # read a MiB at a time: read(MAX_CSV_BYTES + 1) set 512 MiB aside at once
        while len(data) <= MAX_CSV_BYTES and (part := handle.read(1 << 20)):
            data += part
    if len(data) > MAX_CSV_BYTES:
        raise ValueError(f"{path}: larger than {MAX_CSV_BYTES // 2**20} MiB: split the recording and fit a part")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text CSV file (not UTF-8 at byte {exc.start})") from None
    del data
    return parse_samples(text, str(path))


def write_csv(
    stream: TextIO, header: Sequence[str], columns: Iterable[np.ndarray], fmt: str | Sequence[str] = "%.6f"
) -> None:
    """Write equal-length columns under ``header`` as CSV rows (``fmt``: one printf format, or one per column), the
    lines ``numpy.savetxt`` writes: ``%.<d>f`` and ``%d`` by ``magnet._kernels.format_rows`` (60,000 rows of 14
    columns in a few tens of ms), any other WRITE_ROWS rows at a time by one ``%`` (savetxt: 1.1 s for those, 0.2 s)."""
    arrays = [np.asarray(c, dtype=float) for c in columns]

    def rows(lo: int, hi: int) -> np.ndarray:  # (n, K) view of the rows' columns stacked (a chunk at a time: 6.7 MB
        return np.stack([a[lo:hi] for a in arrays]).T  # of fresh memory for 60,000 rows of 14 at once)

    count = len(arrays[0]) if arrays else 0
    if any(a.shape != (count,) for a in arrays):
        raise ValueError(f"columns to write must be 1-D and of one length, got {[a.shape for a in arrays]}")
    formats = [fmt] * len(arrays) if isinstance(fmt, str) else list(fmt)
    row = ",".join(formats) + "\n"
    stream.write(",".join(header) + "\n")
    decimals = [_decimals(f) for f in formats]
    if all(d is not None for d in decimals):  # the same characters, from magnet._kernels.format_rows (5x faster)
        codes = bytes(255 if d == -1 else d for d in decimals if d is not None)
        binary = _bytes_below(stream)
        for lo in range(0, count, WRITE_ROWS * 4):
            text = _kernels.format_rows(rows(lo, lo + WRITE_ROWS * 4), codes)
            if binary is not None:
                binary.write(text)
            else:
                stream.write(text.decode("ascii"))
        return
    for lo in range(0, count, WRITE_ROWS):
        part = rows(lo, lo + WRITE_ROWS)
        stream.write((row * len(part)) % tuple(part.ravel().tolist()))


def _bytes_below(stream: TextIO) -> BinaryIO | None:
    """The binary stream below a text stream (``sys.stdout``) whose text in ASCII is its bytes as they are (UTF-8 or
    ASCII, lines ended by ``\\n``), flushed, for rows formatted as bytes (no str made of them and encoded again: a
    tenth of the writing); None for any other stream."""
    binary, encoding = getattr(stream, "buffer", None), getattr(stream, "encoding", None)
    if binary is None or not encoding or os.linesep != "\n" or codecs.lookup(encoding).name not in ("utf-8", "ascii"):
        return None
    stream.flush()
    return binary


def _decimals(fmt: str) -> int | None:
    """The decimals of a ``%.<d>f`` format (d up to 20), -1 for ``%d``, None for any other format (written by ``%``)."""
    if fmt == "%d":
        return -1
    match = re.fullmatch(r"%\.(\d{1,2})f", fmt)
    return None if match is None or int(match.group(1)) > 20 else int(match.group(1))


def gyro_columns(table: SampleTable) -> np.ndarray | None:
    """gx,gy,gz (N, 3) rad/s when the file has all three, else None."""
    if not all(c in table.columns for c in GYRO_COLUMNS):
        return None
    return np.column_stack([table.numeric(c) for c in GYRO_COLUMNS])


def sample_period_s(table: SampleTable, rate_hz: float | None) -> float:
    """The gyroscope's sample period: 1 / --rate, else from the t_s column; ValueError naming both when neither."""
    if rate_hz is not None:
        if not 0.5 <= rate_hz <= 10_000:
            raise ValueError(f"--rate {rate_hz} Hz is outside 0.5 .. 10000 Hz")
        return 1.0 / rate_hz
    if "t_s" not in table.columns:
        raise ValueError(
            f"{table.path}: the gyroscope columns gx,gy,gz need the sample times: add a t_s column "
            "(seconds) or give --rate HZ"
        )
    from magnet.attitude import fusion  # the filter's package: loaded only when the times are needed

    return fusion.sample_period_s(table.numeric("t_s"))
