"""What the readers of recordings take (``InputOptions``) and what a reader is (``Reader``): their own module, so
that the readers (``ulog.py``, ``dataflash.py``, ``tlog.py``) and the table of readers (``inputs.py``) import them
without a circle."""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from pathlib import Path

from services.common.csvio import SampleTable


@dataclasses.dataclass(frozen=True)
class InputOptions:
    """What to take from a recording that holds more than one stream.

    mag: the magnetometer instance (0 = the first) of a flight log, None for the reader's default; topic: the topic
    of a ROS 2 recording, None for the reader's choice (the one magnetometer topic it holds)."""

    mag: int | None = None
    topic: str | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> InputOptions:
        return cls(getattr(args, "mag", None), getattr(args, "topic", None))


Reader = Callable[[Path, InputOptions], SampleTable]
