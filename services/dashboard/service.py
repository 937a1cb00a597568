"""``magnet dashboard [--http HOST:PORT] [--token T] [--location LAT,LON] [Zenoh options]``: a live web page.

Joins the Zenoh network like any other subscriber (liveliness of devices, headings, calibration progress and
records), and serves the page at ``http://127.0.0.1:8080`` unless told otherwise (``--http``; it binds 127.0.0.1
unless given another address). Calibration control from the page needs a token: ``--token``, else
``$MAGNET_DASHBOARD_TOKEN``, else a random one printed at start together with the address to open.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import logging
import os
import secrets
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import zenoh

from magnet import wire
from services.common import metrics
from services.common.endpoint import use_local_pipeline
from services.common.guard import Guard
from services.common.status_board import StatusBoard
from services.common.zenoh_session import open_session, session_mode
from services.dashboard.settings import (
    DEFAULT_HTTP,
    TOKEN_ENV,
    DashboardSettings,
    add_arguments,
    is_loopback,
    parse_http,
    settings_from_args,
)

if TYPE_CHECKING:
    from magnet.earth.geomag import EarthField
    from services.dashboard.gate import Gate
    from services.dashboard.state import FleetState

log = logging.getLogger("magnet.dashboard")
#: an idle keep-alive connection is closed after this (a slow or silent client holds no connection for long)
KEEP_ALIVE_S = 5
#: connections at once (event streams included, limited further by ``app.MAX_STREAMS``): past it a connection is
#: answered 503 where it is accepted (``gate.Gate``), before uvicorn makes anything for it, instead of a file and a
#: task per connection until the process's file limit
MAX_CONNECTIONS = 256
#: a message logged over and over (uvicorn's 503s) goes to the log once per this many seconds, with its count
LOG_EVERY_S = 10.0

#: the batch size the dashboard's links negotiate (bytes; Zenoh's default 65,535): every message received is a slice
#: of the batch it came in, so a sample waiting in a ring keeps that whole buffer. A flood's headings and progress,
#: sent a few to a batch, held 64 kB each in the rings of 1,024: the dashboard's RSS rose 13-21 MB within each flood
#: of 20,000 ids (a reproduction; 20-40 MB in the soak) and 2-4 MB with batches of 8 kB. The dashboard receives small
#: messages (larger ones, replies and the raw messages it refuses, are cut into fragments and joined again); a
#: --config file replaces this
BATCH_BYTES = 8192
ZENOH_DEFAULTS = {"transport/link/tx/batch_size": str(BATCH_BYTES)}

__all__ = ["add_arguments", "page_address", "run"]


def _earth(settings: DashboardSettings) -> EarthField | None:
    if not settings.location:
        return None
    from magnet.earth.geomag import earth_field
    from magnet.earth.location import Location

    return earth_field(*Location.parse(settings.location).as_tuple(), settings.date)


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
    use_local_pipeline(args)  # no Zenoh option given: the magnet up of this user, if one runs
    return serve(settings_from_args(args))


def serve(settings: DashboardSettings) -> int:
    """Serve the page until asked to stop; 2 when the address cannot be bound."""
    import uvicorn

    from services.dashboard.app import create_app
    from services.dashboard.ingest import Control, Ingest
    from services.dashboard.state import FleetState

    host, port = settings.address
    if settings.http is None and f"{host}:{port}" != DEFAULT_HTTP:
        print(f"magnet dashboard: {DEFAULT_HTTP} is taken (by magnet up's own dashboard?): serving on {host}:{port}")
    token = settings.token or os.environ.get(TOKEN_ENV) or secrets.token_urlsafe(12)
    prefix = settings.zenoh.prefix
    places = {entry.device: entry.location for entry in settings.places if entry.location is not None}
    state = FleetState(
        _earth(settings),
        date=settings.date,
        places=places,
        max_rows=settings.max_devices,
        forget_after_s=settings.forget_after_s,
    )
    with contextlib.ExitStack() as stack:
        session = stack.enter_context(open_session(settings.zenoh, ZENOH_DEFAULTS))
        stack.enter_context(session.liveliness().declare_token(wire.liveliness_key(prefix, "dashboard", "dashboard")))
        board = _metrics_board(settings, state)
        own = session_mode(settings.zenoh) == "client"  # behind a router: the tokens on sessions of their own, renewed
        opener = functools.partial(open_session, settings.zenoh, ZENOH_DEFAULTS) if own else None
        ingest = stack.enter_context(
            Ingest(session, prefix, state, tick_s=settings.refresh_s, metrics_board=board, opener=opener)
        )
        if board is not None:  # what the ingest thread wrote, never the rows (scrapes run on their own thread)
            metrics.start(settings.metrics, "dashboard", board.read)
        thread = threading.Thread(target=ingest.run, name="dashboard-ingest", daemon=True)
        thread.start()
        stack.callback(thread.join, 5)
        stack.callback(ingest.stop.set)
        _start_foxglove(stack, session, settings, token)
        app = create_app(
            state,
            Control(session, prefix),
            token,
            view_needs_token=not is_loopback(host),
            interval_s=settings.refresh_s,
            operator=operator_name(settings.operator),
            allowed_hosts=settings.allowed_hosts,
        )
        config = uvicorn.Config(
            app,
            host=host,
            port=port,
            log_level="warning",
            access_log=False,
            timeout_graceful_shutdown=1,
            timeout_keep_alive=KEEP_ALIVE_S,
            limit_concurrency=MAX_CONNECTIONS,
            http=http_protocol(),  # type: ignore[arg-type]
            lifespan="off",
        )
        server = _Server(config, app.state.dashboard)
        print(f"magnet dashboard: {page_address(host, port, token)}  (control token: {token})", flush=True)
        logging.getLogger("uvicorn.error").addFilter(OncePer(LOG_EVERY_S))  # its 503s: one line per round of them
        with contextlib.suppress(SystemExit):  # uvicorn exits when it cannot bind
            server.run()
        app.state.dashboard.events.close()
    if not server.started:
        print(f"magnet dashboard: could not serve on {host}:{port} (is the port in use?)", file=sys.stderr)
        return 2
    return 0


def http_protocol() -> Gate:
    """uvicorn's ``http`` for the dashboard: past ``MAX_CONNECTIONS`` refused at accept (``gate.Gate``); each
    admitted connection with a deadline for its request head and a write-stall limit (``http_limits.BoundedH11``)."""
    from services.dashboard.gate import Gate
    from services.dashboard.http_limits import BoundedH11

    return Gate(BoundedH11, MAX_CONNECTIONS)


def _metrics_board(settings: DashboardSettings, state: FleetState) -> StatusBoard | None:
    """With ``--metrics``, the board the ingest thread writes ``state.metrics_status()`` on (``ingest
    .METRICS_REFRESH_S``) and a scrape reads (issue 32: it walked the rows on the metrics server's thread); None
    without."""
    from services.dashboard.ingest import METRICS_REFRESH_S

    if not settings.metrics:
        return None
    guard = Guard("dashboard", log, state.dropped)
    return StatusBoard(wire.status_key(settings.zenoh.prefix, "dashboard"), guard, refresh_s=METRICS_REFRESH_S)


def _start_foxglove(
    stack: contextlib.ExitStack, session: zenoh.Session, settings: DashboardSettings, token: str
) -> None:
    """The Foxglove bridge in its own thread when ``--foxglove`` is given (``services.dashboard.foxglove``), behind
    the dashboard's token and host names (``foxglove_front``); stopped and its subscribers undeclared when ``stack``
    closes."""
    if not settings.foxglove:
        return
    from services.dashboard.foxglove import FoxgloveBridge
    from services.dashboard.foxglove_front import view_token
    from services.dashboard.hosts import LOOPBACK_NAMES, host_name

    host, port = parse_http(settings.foxglove)
    told = {host_name(h) for h in settings.allowed_hosts} | ({host} if host not in ("0.0.0.0", "::", "") else set())
    allowed = LOOPBACK_NAMES | told
    bridge = stack.enter_context(FoxgloveBridge(session, settings.zenoh.prefix, host, port, token, allowed))
    thread = threading.Thread(target=bridge.run, name="dashboard-foxglove", daemon=True)
    thread.start()
    stack.callback(thread.join, 5)
    stack.callback(bridge.stop.set)
    shown = f"[{host}]" if ":" in host else host
    print(
        f"magnet dashboard: Foxglove WebSocket at ws://{shown}:{bridge.port}/?token={view_token(token)}  (give the "
        "Foxglove app this address; other clients may send the control token in Authorization: Bearer)",
        flush=True,
    )


class OncePer(logging.Filter):
    """Lets a message through once per ``every_s`` seconds, saying how many like it were held back meanwhile:
    uvicorn logs "Exceeded concurrency limit." for every 503 it answers (2,000 lines for a burst of streams)."""

    def __init__(self, every_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__()
        self.every_s, self.clock = every_s, clock
        self.last: dict[str, tuple[float, int]] = {}  # message -> (when last let through, held back since)

    def filter(self, record: logging.LogRecord) -> bool:
        message, now = str(record.msg), self.clock()
        when, held = self.last.get(message, (-1e18, 0))
        if now - when < self.every_s:
            self.last[message] = (when, held + 1)
            return False
        if held:
            record.msg = f"{record.msg} ({held} more like it in the last {now - when:.0f} s)"
        if len(self.last) > 256:
            self.last.clear()
        self.last[message] = (now, 0)
        return True


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
