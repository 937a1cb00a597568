"""What the flight-log readers share: the streams one log gives, turned into the offline commands' ``SampleTable``.

A reader (``services.common.inputs.ulog``, ``.dataflash``, ``.tlog``) finds in its log the magnetometer instance
asked for (uT, body frame FRD, raw where the log has it), the accelerometer (m/s^2) and gyroscope (rad/s) in the
body frame, battery current (A) and throttle (0..1) where logged, each with its own times; ``to_table`` resamples
them all at the magnetometer's times (linear interpolation, ``magnet.autopilot.conventions.align``) and names the
columns as a CSV would: ``t_s`` (s, the log's own clock), ``ax,ay,az``, ``gx,gy,gz``, ``current_a``, ``throttle``.
Every problem is a ``ValueError`` naming the file.

``ReferenceYaw`` is the autopilot's own heading estimate in the log, for ``magnet heading --compare``.
"""

from __future__ import annotations

import array
import contextlib
import dataclasses
import gc
import io
import os
import sys
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from magnet.autopilot.conventions import align, increasing
from services.common.inputs.csvio import MAX_READING, SampleTable

#: fewer magnetometer samples than this and a log is refused as too short to be of use
MIN_MAG_SAMPLES = 2


@dataclasses.dataclass(frozen=True, eq=False)
class Stream:
    """One logged quantity: t_us (M,) microseconds on the log's clock, values (M,) or (M, K)."""

    t_us: np.ndarray
    values: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class LogStreams:
    """What a reader found. mag: (N, 3) uT body frame at mag.t_us; acc m/s^2 and gyr rad/s (M, 3) body frame or
    None; extra: named (M,) streams (``current_a`` A, ``throttle`` 0..1); note: which streams, in words."""

    mag: Stream
    acc: Stream | None
    gyr: Stream | None
    extra: dict[str, Stream]
    note: str


@dataclasses.dataclass(frozen=True, eq=False)
class ReferenceYaw:
    """The autopilot's logged heading: t_s (M,) s on the log's clock, yaw_deg (M,) clockwise from north; source: the
    message it came from; declination: what the autopilot was told of the declination, in words."""

    t_s: np.ndarray
    yaw_deg: np.ndarray
    source: str
    declination: str


class Table:
    """The kept numbers of one record type: ``names`` (the fields its records have, in ``KEPT_FIELDS``' order) and
    ``rows`` (N, len(names)) float, grown a record at a time in a flat ``array('d')``."""

    def __init__(self, names: tuple[str, ...], fields: tuple[str, ...] = ()) -> None:
        self.names = names
        self.fields = fields or names  # every field the records have, kept or not (for messages)
        self._flat = array.array("d")

    @classmethod
    def of(cls, names: tuple[str, ...], records: list[Any]) -> Table:
        """The table of the fields ``names`` that ``records`` have (their attributes, as the first has them)."""
        table = cls(tuple(n for n in names if records and hasattr(records[0], n)))
        for record in records:
            table.add(record)
        return table

    def add(self, record: Any) -> None:
        """Append the fields ``names`` of a record (its attributes)."""
        self._flat.extend(float(getattr(record, name)) for name in self.names)

    def add_row(self, values: Iterable[float]) -> None:
        self._flat.extend(values)

    def __len__(self) -> int:
        return len(self._flat) // max(len(self.names), 1)

    def column(self, name: str) -> np.ndarray:
        return self.columns((name,))[:, 0]

    def columns(self, names: tuple[str, ...]) -> np.ndarray:
        """(N, len(names)) of the fields ``names``; ValueError naming the first the records lack."""
        missing = [n for n in names if n not in self.names]
        if missing:
            raise ValueError(f"the log's records lack the field {missing[0]} (they have {', '.join(self.names)})")
        return self.rows[:, [self.names.index(n) for n in names]]

    def where(self, keep: np.ndarray) -> Table:
        table = Table(self.names, self.fields)
        table._flat = array.array("d", self.rows[keep].ravel())
        return table

    @property
    def rows(self) -> np.ndarray:
        return np.frombuffer(self._flat, dtype=float).reshape(-1, len(self.names))


def _clean(stream: Stream) -> Stream:
    """The samples with finite values and strictly increasing times."""
    values = np.asarray(stream.values, dtype=float)
    finite = np.isfinite(values) if values.ndim == 1 else np.isfinite(values).all(axis=1)
    t = np.asarray(stream.t_us, dtype=float)[finite]
    values = values[finite]
    keep = increasing(t)
    return Stream(t[keep], values[keep])


def _plausible(path: Path, what: str, stream: Stream) -> Stream:
    """``stream`` when no reading is beyond +-MAX_READING (the CSV reader's check); ValueError naming the first."""
    beyond = np.abs(stream.values) > MAX_READING
    if beyond.any():
        row = int(np.argmax(beyond.reshape(len(beyond), -1).any(axis=1)))
        raise ValueError(
            f"{path}: {what} sample {row + 1} (t={stream.t_us[row] / 1e6:.6g} s) reads "
            f"{np.max(np.abs(stream.values[row])):.3g}, beyond +-{MAX_READING:.0e}: no sensor reads that in any "
            "unit (a damaged log)"
        )
    return stream


def to_table(path: Path, streams: LogStreams) -> SampleTable:
    """The SampleTable of ``streams``: every stream resampled at the magnetometer's times; ValueError naming the file
    when it holds fewer than MIN_MAG_SAMPLES magnetometer samples, or a sensor reading beyond +-MAX_READING."""
    mag = _plausible(path, "magnetometer", _clean(streams.mag))
    if len(mag.t_us) < MIN_MAG_SAMPLES:
        raise ValueError(f"{path}: the log holds {len(mag.t_us)} usable magnetometer samples: nothing to work with")
    t = mag.t_us
    columns: dict[str, list[str] | np.ndarray] = {"t_s": t / 1e6}
    acc = None
    for stream, names in ((streams.acc, ("ax", "ay", "az")), (streams.gyr, ("gx", "gy", "gz"))):
        if stream is None:
            continue
        clean = _plausible(path, "accelerometer" if names[0] == "ax" else "gyroscope", _clean(stream))
        if len(clean.t_us) < 2:
            continue
        resampled = align(t, clean.t_us, clean.values)
        columns.update({name: resampled[:, k] for k, name in enumerate(names)})
        if names[0] == "ax":
            acc = resampled
    for name, stream in streams.extra.items():
        clean = _clean(stream)
        if len(clean.t_us) >= 1:
            columns[name] = (
                align(t, clean.t_us, clean.values) if len(clean.t_us) > 1 else np.full(len(t), clean.values[0])
            )
    return SampleTable(str(path), mag.values, acc, columns, note=streams.note)


def described(streams: list[str]) -> str:
    """``a, b and c`` for a list of stream descriptions."""
    return streams[0] if len(streams) == 1 else ", ".join(streams[:-1]) + " and " + streams[-1]


def release_unclosed() -> None:
    """Collect what a failed parse left behind (pymavlink's open file, when its constructor raised) without the
    ResourceWarning the collector would print: the caller reports the failure in its own one line."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ResourceWarning)
        gc.collect()


@contextlib.contextmanager
def silenced() -> Iterator[None]:
    """Standard output and error silenced, down to the file descriptors: pymavlink's DataFlash indexer (C) prints
    each bad header it skips, thousands of lines for a damaged log, which the reader's one error line replaces."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])


def read_pymavlink(
    path: Path,
    types: list[str],
    what: str,
    take: Callable[[Any], None],
    *,
    quiet_open: bool = False,
    opener: Callable[[str], Any] | None = None,
    **options: Any,
) -> None:
    """Hand each message of ``types`` in the log at ``path`` to ``take``, in order, through pymavlink's
    ``mavlink_connection(path, **options)``, with what pymavlink prints silenced (down to the file descriptors while
    it opens the file when ``quiet_open``: see ``silenced``); ``opener(path)`` instead when given. Any failure,
    pymavlink's or ``take``'s, is one ValueError: ``{path}: not a readable {what} (...)``."""
    from pymavlink import mavutil

    failure = ""
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            with silenced() if quiet_open else contextlib.nullcontext():
                log = opener(str(path)) if opener else mavutil.mavlink_connection(str(path), **options)
            try:
                while (message := log.recv_match(type=types)) is not None:
                    take(message)
            finally:
                log.close()
    except Exception as exc:  # pymavlink raises whatever its parser meets in a damaged file
        failure = f"{type(exc).__name__}: {exc}"
    if failure:
        release_unclosed()  # pymavlink leaves its file open when its constructor fails
        raise ValueError(f"{path}: not a readable {what} ({failure})")
