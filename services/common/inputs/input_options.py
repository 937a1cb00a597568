"""What the readers of recordings take (``InputOptions``) and what a reader is (``Reader``): their own module, so
that the readers (``ulog.py``, ``dataflash.py``, ``tlog.py``) and the table of readers (``inputs.py``) import them
without a circle."""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

from services.common.inputs.csvio import SampleTable
from services.common.options import at_least, check_options, from_args, option


def _instance(value: Any) -> str | None:
    return None if value is None else at_least(0)(value)


@dataclasses.dataclass(frozen=True)
class InputOptions:
    """What to take from a recording that holds more than one stream (declared once: ``services.common.options``).

    mag: the magnetometer instance (0 = the first) of a flight log, None for the reader's default; topic: the topic
    of a ROS 2 recording, None for the reader's choice (the one magnetometer topic it holds)."""

    mag: int | None = option(
        None, "--mag", parse=int, metavar="N", check=_instance, help="flight logs: the magnetometer instance to read"
    )
    topic: str | None = option(
        None, "--topic", metavar="TOPIC", help="ROS 2 recordings: the MagneticField topic to read"
    )

    def __post_init__(self) -> None:
        check_options(self)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> InputOptions:
        """The options ``inputs.add_input_arguments`` added (unset on a parser without them)."""
        return from_args(cls, args)


Reader = Callable[[Path, InputOptions], SampleTable]
