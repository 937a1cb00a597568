"""``magnet dashboard [--http HOST:PORT] [--token T] [--location LAT,LON] [Zenoh options]``: a live web page.

Joins the Zenoh network like any other subscriber (liveliness of devices, headings, calibration progress and
records), and serves the page at ``http://127.0.0.1:8080`` unless told otherwise (``--http``; it binds 127.0.0.1
unless given another address). Calibration control from the page needs a token: ``--token``, else
``$MAGNET_DASHBOARD_TOKEN``, else a random one printed at start together with the address to open.
"""

from __future__ import annotations

import argparse
import ipaddress
import logging
import os
import secrets
import sys
import threading

from services.common import metrics
from services.common.endpoint import use_local_pipeline
from services.common.zenoh_session import add_zenoh_arguments, open_session

log = logging.getLogger("magnet.dashboard")

DEFAULT_HTTP = "127.0.0.1:8080"
TOKEN_ENV = "MAGNET_DASHBOARD_TOKEN"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--http",
        default=DEFAULT_HTTP,
        metavar="HOST:PORT",
        help=f"where the page is served (default {DEFAULT_HTTP}; loopback unless told otherwise)",
    )
    parser.add_argument("--token", help=f"control token (default ${TOKEN_ENV}, else a random one printed at start)")
    parser.add_argument(
        "--location",
        metavar="LAT,LON[,ALT_M]",
        help="where the devices are: |B| and dip are shown against the World Magnetic Model there",
    )
    parser.add_argument("--date", metavar="YYYY-MM-DD", help="date for the World Magnetic Model (default today)")
    parser.add_argument(
        "--refresh", type=float, default=0.25, help="seconds between updates of the page (default 0.25: 4 per second)"
    )
    parser.add_argument(
        "--foxglove",
        metavar="HOST:PORT",
        help="also serve the fleet to the Foxglove app over its WebSocket protocol here (e.g. 127.0.0.1:8765)",
    )
    parser.add_argument(
        "--operator",
        metavar="NAME",
        help="name recorded (as 'by') with the commits and rollbacks made from the page (default: user@host)",
    )
    metrics.add_metrics_argument(parser)
    add_zenoh_arguments(parser)


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


def _earth(args: argparse.Namespace):
    if not args.location:
        if args.date:
            raise ValueError("--date needs --location")
        return None
    from magnet.geomag import earth_field
    from magnet.place import Location

    return earth_field(*Location.parse(args.location).as_tuple(), args.date)


def page_address(host: str, port: int, token: str) -> str:
    """The address to open (with the token, which the page keeps and removes from the address bar)."""
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/?token={token}"


def operator_name(given: str | None) -> str:
    """Who the page's commits and rollbacks are recorded as made by: ``--operator``, else the OS user of the
    dashboard (user@host); only the characters a selector parameter carries."""
    if not given:
        import getpass
        import socket

        try:
            given = f"{getpass.getuser()}@{socket.gethostname()}"
        except (KeyError, OSError):
            given = "dashboard"
    return "".join(c for c in given if c.isalnum() or c in "@.-_")[:128] or "dashboard"


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from magnet import wire
    from services.dashboard.app import create_app
    from services.dashboard.ingest import Control, Ingest
    from services.dashboard.state import FleetState

    host, port = parse_http(args.http)
    if not 0.05 <= args.refresh <= 10:
        raise ValueError(f"--refresh must be 0.05..10 seconds, got {args.refresh}")
    token = args.token or os.environ.get(TOKEN_ENV) or secrets.token_urlsafe(12)
    use_local_pipeline(args)  # no Zenoh option given: the magnet up of this user, if one runs
    state = FleetState(_earth(args))
    if args.metrics:
        metrics.parse_address(args.metrics)
    with open_session(args) as session:
        metrics.start(args.metrics, "dashboard", state.metrics_status)
        token_alive = session.liveliness().declare_token(wire.liveliness_key(args.prefix, "dashboard", "dashboard"))
        ingest = Ingest(session, args.prefix, state, tick_s=args.refresh)
        thread = threading.Thread(target=ingest.run, name="dashboard-ingest", daemon=True)
        thread.start()
        foxglove = _start_foxglove(session, args)
        app = create_app(
            state,
            Control(session, args.prefix),
            token,
            view_needs_token=not is_loopback(host),
            interval_s=args.refresh,
            operator=operator_name(args.operator),
        )
        config = uvicorn.Config(
            app,
            host=host,
            port=port,
            log_level="warning",
            access_log=False,
            timeout_graceful_shutdown=1,
            lifespan="off",
        )
        server = _Server(config, app.state.dashboard)
        print(f"magnet dashboard: {page_address(host, port, token)}  (control token: {token})", flush=True)
        try:
            server.run()
        except SystemExit:  # uvicorn exits when it cannot bind
            pass
        finally:
            ingest.stop.set()
            thread.join(timeout=5)
            if foxglove is not None:
                foxglove.stop.set()
            token_alive.undeclare()
    if not server.started:
        print(f"magnet dashboard: could not serve on {host}:{port} (is the port in use?)", file=sys.stderr)
        return 2
    return 0


def _start_foxglove(session, args: argparse.Namespace):
    """The Foxglove bridge in its own thread when ``--foxglove`` is given (``services.dashboard.foxglove``)."""
    if not args.foxglove:
        return None
    from services.dashboard.foxglove import FoxgloveBridge

    host, port = parse_http(args.foxglove)
    bridge = FoxgloveBridge(session, args.prefix, host, port)
    threading.Thread(target=bridge.run, name="dashboard-foxglove", daemon=True).start()
    print(f"magnet dashboard: Foxglove WebSocket at ws://{host}:{bridge.port}", flush=True)
    return bridge


class _Server:
    """uvicorn's server, ending the event streams when it is asked to stop (Ctrl-C, SIGTERM)."""

    def __init__(self, config, dashboard) -> None:
        import uvicorn

        dashboard_ = dashboard

        class Server(uvicorn.Server):
            def handle_exit(self, sig, frame):
                dashboard_.stopping.set()
                super().handle_exit(sig, frame)

        self.server = Server(config)

    @property
    def started(self) -> bool:
        return bool(self.server.started)

    def run(self) -> None:
        self.server.run()
