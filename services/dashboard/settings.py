"""The settings of ``magnet dashboard``, declared once (``services.common.options``): where the page is served, the
control token, where the devices are (for the World Magnetic Model), the page's refresh, the Foxglove bridge, the
operator's name, and the Zenoh options."""

from __future__ import annotations

import argparse
import dataclasses
import ipaddress
import socket

from magnet.fleet.places import PlaceEntry
from services.common import metrics
from services.common.options import add_options, at_least, check_options, from_args, option
from services.common.places_options import add_fleet_argument, read_fleet
from services.common.zenoh_session import ZenohSettings, add_zenoh_arguments
from services.dashboard.state import FORGET_AFTER_S, MAX_ROWS

DEFAULT_HTTP = "127.0.0.1:8080"
TOKEN_ENV = "MAGNET_DASHBOARD_TOKEN"


def parse_http(text: str) -> tuple[str, int]:
    """(host, port) from ``HOST:PORT`` (``[v6]:PORT`` too); ValueError saying what is wrong."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host:
        raise ValueError(f"--http {text!r} must be HOST:PORT, e.g. {DEFAULT_HTTP}")
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"--http {text!r}: the port must be a number") from None
    if not 0 <= number <= 65535:
        raise ValueError(f"--http {text!r}: the port must be 0..65535")
    return host, number


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _forget_after(value: float) -> str | None:
    return None if value >= 1 else "must be at least 1 second"


def _refresh(value: float) -> str | None:
    return None if 0.05 <= value <= 10 else "must be 0.05..10 seconds"


@dataclasses.dataclass(frozen=True)
class DashboardSettings:
    """Everything ``magnet dashboard`` runs with; ``metrics`` (``--metrics``, shared with the other services) and
    ``zenoh`` are set from their own options."""

    http: str | None = option(
        None,
        "--http",
        metavar="HOST:PORT",
        help=f"where the page is served (default {DEFAULT_HTTP}, or a free loopback port while that one is taken, "
        "by magnet up's dashboard say)",
        show_default=False,
    )
    token: str | None = option(
        None, "--token", help=f"control token (default ${TOKEN_ENV}, else a random one printed at start)"
    )
    location: str | None = option(
        None,
        "--location",
        metavar="LAT,LON[,ALT_M]",
        help="where the devices are: |B| and dip are shown against the World Magnetic Model there",
    )
    date: str | None = option(
        None, "--date", metavar="YYYY-MM-DD", help="date for the World Magnetic Model (default today)"
    )
    refresh_s: float = option(
        0.25,
        "--refresh",
        check=_refresh,
        help="seconds between updates of the page (default 0.25: 4 per second)",
        show_default=False,
    )
    foxglove: str | None = option(
        None,
        "--foxglove",
        metavar="HOST:PORT",
        help="also serve the fleet to the Foxglove app over its WebSocket protocol here (e.g. 127.0.0.1:8765)",
    )
    allow_host: str | None = option(
        None,
        "--allow-host",
        metavar="NAME[,NAME...]",
        help="host names the page may be opened by besides the loopback ones and the --http address (a request "
        "naming another Host, or coming from another site's page, is refused: DNS rebinding)",
    )
    operator: str | None = option(
        None,
        "--operator",
        metavar="NAME",
        help="name recorded (as 'by') with the commits and rollbacks made from the page (default: user@host)",
    )
    max_devices: int = option(
        MAX_ROWS,
        "--max-devices",
        check=at_least(1),
        help="rows of the fleet table kept at most; beyond, the least recently heard-of device's row is forgotten",
    )
    forget_after_s: float = option(
        FORGET_AFTER_S,
        "--forget-after",
        metavar="SECONDS",
        check=_forget_after,
        help="forget a device's row when nothing was heard of it for this long and its liveliness token is gone",
    )
    metrics: str | None = None
    zenoh: ZenohSettings = ZenohSettings()
    places: tuple[PlaceEntry, ...] = ()  # the --fleet file's entries: each device's place where it reports none

    def __post_init__(self) -> None:
        check_options(self)
        parse_http(self.http or DEFAULT_HTTP)
        if self.foxglove is not None:
            parse_http(self.foxglove)
        if self.date and not self.location:
            raise ValueError("--date needs --location")
        if self.metrics:
            metrics.parse_address(self.metrics)

    @property
    def allowed_hosts(self) -> tuple[str, ...]:
        """Names a request's Host may give besides the loopback ones: ``--allow-host`` and the ``--http`` host
        (unless it is a wildcard)."""
        host = self.address[0]
        told = tuple(n.strip() for n in (self.allow_host or "").split(",") if n.strip())
        return told + (() if host in ("0.0.0.0", "::", "") else (host,))

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) where the page is served: ``--http``, else ``default_http()``'s."""
        return parse_http(self.http or default_http())


def bindable(address: str) -> bool:
    """Whether a server could listen on ``address`` (HOST:PORT) now; a port left in TIME_WAIT by a server that just
    stopped counts as free, as it is for the server itself (uvicorn sets SO_REUSEADDR too)."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind(parse_http(address))
        except OSError:
            return False
    return True


def free_loopback_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def default_http(preferred: str = DEFAULT_HTTP) -> str:
    """``preferred`` while it is free, else a free loopback port (``magnet up``'s dashboard holds 8080, say)."""
    return preferred if bindable(preferred) else f"127.0.0.1:{free_loopback_port()}"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, DashboardSettings)
    add_fleet_argument(parser)
    metrics.add_metrics_argument(parser)
    add_zenoh_arguments(parser)


def settings_from_args(args: argparse.Namespace) -> DashboardSettings:
    places = tuple(read_fleet(args.fleet).values())
    return from_args(DashboardSettings, args, metrics=args.metrics, zenoh=ZenohSettings.from_args(args), places=places)
