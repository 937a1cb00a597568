"""The options of a MAVLink connection: a pymavlink URL (``udpin:HOST:PORT``, ``udpout:HOST:PORT``, ``tcp:HOST:PORT``
or a serial device) under the command's own flag, and ``--baud`` for a serial device. Shared by ``magnet edge
--mavlink`` (declared as settings fields: ``url_option``, ``baud_option``) and ``magnet export --apply``
(``add_mavlink_url_arguments``); the default and the checks are written here once."""

from __future__ import annotations

import argparse
from typing import Any

from services.common.options import option

#: the baud rate of a serial MAVLink link when none is given
DEFAULT_BAUD = 57600
MIN_BAUD, MAX_BAUD = 50, 10_000_000
#: pymavlink's network links: KIND:HOST:PORT (anything else is a serial device path)
NETWORK_LINKS = ("udpin", "udpout", "udp", "udpbcast", "tcp", "tcpin")


def check_url(url: Any) -> str | None:
    """What is wrong with a MAVLink URL (None: nothing, or no URL): a network link needs HOST:PORT, port 1..65535."""
    if url is None:
        return None
    if not url:
        return "needs a URL: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or a device"
    kind, colon, rest = url.partition(":")
    if kind not in NETWORK_LINKS:
        # a serial device is a path (/dev/ttyACM0, COM3); a word before a colon is a link kind pymavlink would misread
        if colon and "/" not in kind and not kind.upper().startswith("COM"):
            kinds = ", ".join(NETWORK_LINKS)
            return f"has an unknown link kind {kind!r}: use KIND:HOST:PORT with KIND one of {kinds}, or a device path"
        return None
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        return f"expects {kind}:HOST:PORT with a port in 1..65535"
    return None


def check_baud(value: Any) -> str | None:
    """A whole number of bits per second in MIN_BAUD..MAX_BAUD."""
    if isinstance(value, bool) or not isinstance(value, int) or not MIN_BAUD <= value <= MAX_BAUD:
        return f"must be {MIN_BAUD}..{MAX_BAUD}"
    return None


def url_option(flag: str, help: str) -> Any:
    """A settings field (``services.common.options``): the URL under ``flag``, None when not given."""
    return option(None, flag, metavar="URL", help=help, check=check_url)


def baud_option(help: str) -> Any:
    """A settings field: ``--baud N`` (default ``DEFAULT_BAUD``)."""
    return option(DEFAULT_BAUD, "--baud", help=help, check=check_baud)


def add_mavlink_url_arguments(parser: argparse.ArgumentParser, flag: str, url_help: str, baud_help: str) -> None:
    """``flag URL`` (``url_help``) and ``--baud N`` (``baud_help``, default ``DEFAULT_BAUD``), for a command whose
    settings are still read from argparse by hand (``magnet export``)."""
    parser.add_argument(flag, metavar="URL", help=url_help)
    parser.add_argument("--baud", type=int, default=DEFAULT_BAUD, help=f"{baud_help} (default {DEFAULT_BAUD})")
