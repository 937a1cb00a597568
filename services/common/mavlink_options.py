"""The options of a MAVLink connection: a pymavlink URL (``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``
or a serial device) under the command's own flag, and ``--baud`` for a serial device. Shared by ``magnet edge
--mavlink`` and ``magnet export --apply``."""

from __future__ import annotations

import argparse

#: the baud rate of a serial MAVLink link when none is given
DEFAULT_BAUD = 57600


def add_mavlink_url_arguments(parser: argparse.ArgumentParser, flag: str, url_help: str, baud_help: str) -> None:
    """``flag URL`` (``url_help``) and ``--baud N`` (``baud_help``, default ``DEFAULT_BAUD``)."""
    parser.add_argument(flag, metavar="URL", help=url_help)
    parser.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=baud_help)
