"""Recorded inputs of the offline commands: one reader per kind of file, chosen by the file's suffix; this package
is their one home (``csvio``, ``ulog``, ``dataflash``, ``tlog``, ``rosbag_input``, what the flight logs share in
``flightlogs``, the options in ``input_options``).

``magnet fit``, ``magnet heading``, ``magnet report`` and ``magnet edge --replay`` read their samples with
``read_input``; each reader returns the same ``SampleTable`` as a CSV gives (``mx,my,mz`` in the file's magnetometer
unit, optional ``ax,ay,az`` m/s^2, ``gx,gy,gz`` rad/s, ``t_s`` s, ``vn,ve,vd`` m/s NED and other named columns).
To read a new kind of recording, write a function ``(path, InputOptions) -> SampleTable`` (``Reader``; both in
``services.common.inputs.input_options``, which the readers import) and add a row per suffix to ``FORMATS`` (the one
table: suffix, reader, and for a flight log the reader of the autopilot's own heading, ``reference_yaw``). Every reader
raises ``ValueError`` naming the file and what to do for a file it cannot use.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from services.common.inputs.csvio import SampleTable, read_samples
from services.common.inputs.input_options import InputOptions as InputOptions  # re-exported for the tests
from services.common.inputs.input_options import Reader
from services.common.options import add_options

if TYPE_CHECKING:  # the flight-log readers load only for flight logs (magnet fit of a CSV never does)
    from services.common.inputs.flightlogs import ReferenceYaw

#: the default: each reader's own choice of stream
NO_OPTIONS = InputOptions()


def _csv(path: Path, options: InputOptions) -> SampleTable:
    return read_samples(path)


def _ulog(path: Path, options: InputOptions) -> SampleTable:
    from services.common.inputs.ulog import read_ulog  # pyulog is loaded only for a ULog

    return read_ulog(path, options)


def _dataflash(path: Path, options: InputOptions) -> SampleTable:
    from services.common.inputs.dataflash import read_dataflash  # pymavlink is loaded only for a log that needs it

    return read_dataflash(path, options)


def _tlog(path: Path, options: InputOptions) -> SampleTable:
    from services.common.inputs.tlog import read_tlog

    return read_tlog(path, options)


def _rosbag(path: Path, options: InputOptions) -> SampleTable:
    from services.common.inputs.rosbag_input import read_rosbag

    return read_rosbag(path, options.topic)


def _ulog_yaw(path: Path) -> ReferenceYaw:
    from services.common.inputs.ulog import ulog_reference_yaw

    return ulog_reference_yaw(path)


def _dataflash_yaw(path: Path) -> ReferenceYaw:
    from services.common.inputs.dataflash import dataflash_reference_yaw

    return dataflash_reference_yaw(path)


def _tlog_yaw(path: Path) -> ReferenceYaw:
    from services.common.inputs.tlog import tlog_reference_yaw

    return tlog_reference_yaw(path)


@dataclasses.dataclass(frozen=True)
class InputFormat:
    """A kind of recording: its ``reader`` and, for a flight log, the reader of the autopilot's own heading estimate
    in it (``reference_yaw``, for ``magnet heading --compare``; None: the file holds none)."""

    reader: Reader
    reference_yaw: Callable[[Path], ReferenceYaw] | None = None


_CSV, _ROSBAG = InputFormat(_csv), InputFormat(_rosbag)
#: the one table of the files the commands read: suffix (lower case, with the dot; "/" for a directory, a rosbag2
#: bag) -> its reader and its reference yaw
FORMATS: dict[str, InputFormat] = {
    ".csv": _CSV,
    ".txt": _CSV,
    ".ulg": InputFormat(_ulog, _ulog_yaw),
    ".bin": InputFormat(_dataflash, _dataflash_yaw),
    ".tlog": InputFormat(_tlog, _tlog_yaw),
    ".mcap": _ROSBAG,
    ".db3": _ROSBAG,
    "/": _ROSBAG,
}


def input_format(path: Path) -> InputFormat:
    """The format of the file (or bag directory) at ``path`` by its suffix: CSV when the suffix is unknown."""
    return FORMATS.get("/" if path.is_dir() else path.suffix.lower(), _CSV)


def add_input_arguments(parser: argparse.ArgumentParser) -> None:
    """``--mag N`` and ``--topic TOPIC`` (``InputOptions``' fields): which stream of a recording to read."""
    add_options(parser, InputOptions)


def read_input(path: str | Path, options: InputOptions = NO_OPTIONS) -> SampleTable:
    """The samples of the recording at ``path``, by its suffix (CSV when unknown); ValueError otherwise."""
    path = Path(path)
    return input_format(path).reader(path, options)


def read_input_told(path: str | Path, options: InputOptions, command: str) -> SampleTable:
    """``read_input``, and the reader's note (which stream of the recording was used) on stderr for the user."""
    table = read_input(path, options)
    if table.note:
        print(f"magnet {command}: {table.note}", file=sys.stderr)
    return table


def reference_yaw(path: str | Path) -> ReferenceYaw:
    """The autopilot's own heading estimate in the flight log at ``path``; ValueError for a file that has none."""
    path = Path(path)
    read = FORMATS.get(path.suffix.lower(), _CSV).reference_yaw
    if read is None:
        raise ValueError(f"{path}: --compare needs a flight log (.ulg, .bin or .tlog) holding the autopilot's attitude")
    return read(path)
