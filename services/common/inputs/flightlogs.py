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

import dataclasses
from pathlib import Path

import numpy as np

from magnet.autopilot.conventions import align, increasing
from services.common.inputs.csvio import SampleTable

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


def _clean(stream: Stream) -> Stream:
    """The samples with finite values and strictly increasing times."""
    values = np.asarray(stream.values, dtype=float)
    finite = np.isfinite(values) if values.ndim == 1 else np.isfinite(values).all(axis=1)
    t = np.asarray(stream.t_us, dtype=float)[finite]
    values = values[finite]
    keep = increasing(t)
    return Stream(t[keep], values[keep])


def to_table(path: Path, streams: LogStreams) -> SampleTable:
    """The SampleTable of ``streams``: every stream resampled at the magnetometer's times; ValueError naming the file
    when it holds fewer than MIN_MAG_SAMPLES magnetometer samples."""
    mag = _clean(streams.mag)
    if len(mag.t_us) < MIN_MAG_SAMPLES:
        raise ValueError(f"{path}: the log holds {len(mag.t_us)} usable magnetometer samples: nothing to work with")
    t = mag.t_us
    columns: dict[str, list[str] | np.ndarray] = {"t_s": t / 1e6}
    acc = None
    for stream, names in ((streams.acc, ("ax", "ay", "az")), (streams.gyr, ("gx", "gy", "gz"))):
        if stream is None:
            continue
        clean = _clean(stream)
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
