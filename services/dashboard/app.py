"""The dashboard's web side (starlette): the page, its static files, plotly.js from the installed wheel, a JSON API
and a server-sent event stream.

Routes:

- ``GET /``: the page; ``GET /static/...``: its files; ``GET /plotly.min.js``: plotly's own bundle (no CDN).
- ``GET /api/fleet``: every row; ``GET /api/devices/{device}``: one device in detail; ``GET /api/vehicles``: every
  vehicle's compasses compared (the compasses' ``@vehicle`` queryable, docs/vehicles.md: the vehicle rows and view);
  ``GET /api/devices/{device}/history?limit=N``: its stored calibrations (asks the calibrator).
- ``GET /api/stream[?device=ID]``: server-sent events: ``fleet`` (rows changed since the last event) every
  ``interval_s``, and ``device`` (the detail of ``device``) every second.
- ``POST /api/devices/{device}/calibrate`` with JSON ``{"action": "start|status|commit|abort", "method": M}`` or
  ``{"action": "rollback", "to": ID}``: the calibrator's session queryable (start, commit and rollback recorded as
  made ``by`` the dashboard's operator). Needs the control token (``Authorization: Bearer TOKEN`` or
  ``X-Magnet-Token``).

Viewing needs no token when the server listens on a loopback address; on any other address every ``/api`` route
needs it too. The token is taken from a header only, never from the address (addresses end up in logs, histories
and ``Referer``s; the page reads its stream with ``fetch``, which sends the header). Bad input gets a 4xx with a JSON
``{"error": ...}`` and changes nothing: 400 malformed, 401 no or wrong token, 404 unknown device, 413 a body over
``MAX_BODY_BYTES`` (refused by its declared length before it is read, and cut off past it), 502/504 when the
calibrator refused or did not answer, 503 past ``MAX_STREAMS`` event streams.

Every request (``HostCheck``) must name in ``Host`` a loopback name or one the dashboard was told to answer to
(``--allow-host``, and the address it listens on), and an ``Origin``, when a browser sends one, must be the page's
own: a web page elsewhere cannot read the fleet through the operator's browser, even by DNS rebinding (403).
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import importlib.util
import logging
import re
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any, Protocol

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from magnet import wire
from services.common.guard import Guard, refusal
from services.common.jsonio import loads_bounded
from services.dashboard.events import FleetEvents, Reader, encode, fleet_body, pieces
from services.dashboard.hosts import LOOPBACK_NAMES, HostCheck, host_name
from services.dashboard.state import FleetState

log = logging.getLogger("magnet.dashboard")

STATIC_DIR = Path(__file__).resolve().parent / "static"
ACTIONS = ("start", "status", "commit", "abort", "rollback")
CALIBRATION_ID = re.compile(r"[0-9a-f]{8,64}")
MAX_BODY_BYTES = 4096
#: event streams at once (each costs a task and a JSON encoding every refresh); past it a new one gets 503
MAX_STREAMS = 64
#: an accepted stream keeps its place this long before it starts (a client gone before it did gives it back)
STARTING_S = 5.0
MAX_HISTORY = 100
DETAIL_EVERY_S = 1.0
Endpoint = Callable[[Request], Awaitable[Response]]


class Control(Protocol):
    """What the page's buttons ask (``services.dashboard.ingest.Control`` over zenoh; a fake in tests)."""

    def calibrate(
        self, device: str, action: str, method: str | None, to: str | None = None, by: str | None = None
    ) -> tuple[list[dict], list[str]]: ...

    def history(self, device: str, limit: int) -> tuple[list[dict], list[str]]: ...

    def vehicles(self) -> tuple[list[dict], list[str]]: ...


def plotly_js_path() -> Path:
    """plotly.min.js inside the installed ``plotly`` package (its package_data), found without importing plotly."""
    spec = importlib.util.find_spec("plotly")
    folders = list(spec.submodule_search_locations or []) if spec is not None else []
    path = Path(folders[0] if folders else ".") / "package_data" / "plotly.min.js"
    if not path.is_file():
        raise OSError(f"plotly.min.js not found at {path}: reinstall the plotly package")
    return path


def error(status: int, message: str) -> JSONResponse:
    return JSONResponse({"error": message}, status_code=status)


class Dashboard:
    """Handlers bound to one FleetState, one Control and one token."""

    def __init__(
        self,
        state: FleetState,
        control: Control,
        token: str,
        view_needs_token: bool,
        interval_s: float = 0.25,
        operator: str = "",
    ) -> None:
        self.state, self.control, self.token, self.operator = state, control, token, operator
        self.view_needs_token, self.interval_s = view_needs_token, interval_s
        self.stopping = asyncio.Event()
        self.streams = 0  # event streams open now
        self.events = FleetEvents(state, interval_s)
        self.starting: list[float] = []  # when each stream accepted but not started yet was accepted (loop time)
        self.guard = Guard("dashboard", log, state.dropped)  # no failing request ends the server or a stream

    def guarded(self, what: str, endpoint: Endpoint) -> Endpoint:
        """``endpoint``, answering 500 with a JSON ``{"error": ...}`` (one log line, counted) when it raises."""

        async def run(request: Request) -> Response:
            try:
                return await endpoint(request)
            except Exception as exc:  # the request fails, the server does not
                self.guard.failed(what, exc)
                return error(500, refusal(exc, "dashboard"))

        return run

    # ---------------------------------------------------------------------------------------------- checks
    def _token_ok(self, request: Request) -> bool:
        given = request.headers.get("x-magnet-token") or ""
        auth = request.headers.get("authorization", "")
        if auth.lower().startswith("bearer "):
            given = auth[7:].strip()
        return bool(given) and hmac.compare_digest(given.encode(), self.token.encode())

    def _view_refused(self, request: Request) -> Response | None:
        if self.view_needs_token and not self._token_ok(request):
            return error(401, "this dashboard listens beyond loopback: give the token (Authorization: Bearer TOKEN)")
        return None

    def _device(self, request: Request) -> str | Response:
        """The path's device id if it is valid and known, else the error response."""
        return self._known(request.path_params["device"])

    def _known(self, device: str) -> str | Response:
        """``device`` if it is a valid id the dashboard has seen, else the error response (400, 404)."""
        try:
            wire.validate_device_id(device)
        except ValueError as exc:
            return error(400, str(exc))
        if not self.state.knows(device):
            return error(404, f"unknown device {device!r}: no message or liveliness token seen for it")
        return device

    # ---------------------------------------------------------------------------------------------- views
    async def index(self, request: Request) -> Response:
        return FileResponse(STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})

    async def plotly(self, request: Request) -> Response:
        return FileResponse(
            plotly_js_path(), media_type="text/javascript", headers={"Cache-Control": "public, max-age=86400"}
        )

    async def fleet(self, request: Request) -> Response:
        refused = self._view_refused(request)
        if refused:
            return refused
        body = await run_in_threadpool(fleet_body, self.state)  # 6 MB for 10,000 rows: not made on the loop
        return Response(body, media_type="application/json")

    async def vehicles(self, request: Request) -> Response:
        """Every vehicle the compasses compare, by name (with shards, the answer that knows most of its compasses)."""
        refused = self._view_refused(request)
        if refused:
            return refused
        answers, errors = await run_in_threadpool(self.control.vehicles)
        found: dict[str, dict[str, Any]] = {}
        for answer in answers:
            name, compasses = answer.get("vehicle"), answer.get("compasses")
            if not isinstance(name, str) or not isinstance(compasses, list):
                continue
            if len(compasses) >= len(found.get(name, {}).get("compasses", [])):
                found[name] = answer
        return JSONResponse({"vehicles": [found[v] for v in sorted(found)], "errors": errors[:10]})

    async def device(self, request: Request) -> Response:
        refused = self._view_refused(request)
        device = refused or self._device(request)
        if isinstance(device, Response):
            return device
        return JSONResponse(self.state.detail(device))

    async def history(self, request: Request) -> Response:
        refused = self._view_refused(request)
        device = refused or self._device(request)
        if isinstance(device, Response):
            return device
        try:
            limit = int(request.query_params.get("limit", "20"))
        except ValueError:
            return error(400, "limit must be a whole number")
        if not 1 <= limit <= MAX_HISTORY:
            return error(400, f"limit must be 1..{MAX_HISTORY}")
        answers, errors = await run_in_threadpool(self.control.history, device, limit)
        records = [r for a in answers for r in (a.get("records") or []) if isinstance(r, dict)]
        if not answers:
            return error(504, "; ".join(errors) or "no calibrator answered for this device's history")
        if not records:  # the calibrator answered: none stored
            return error(404, f"no calibration is stored for {device} (the calibrator has none)")
        changes = [c for a in answers for c in (a.get("changes") or [])]
        return JSONResponse({"device": device, "records": records[:limit], "changes": changes[:limit]})

    # ---------------------------------------------------------------------------------------------- control
    async def calibrate(self, request: Request) -> Response:
        if not self._token_ok(request):
            return error(401, "calibration control needs the dashboard's token (printed at its start)")
        device = self._device(request)
        if isinstance(device, Response):
            return device
        body = await _bounded_body(request, MAX_BODY_BYTES)
        if body is None:
            return error(413, f"request body larger than {MAX_BODY_BYTES} bytes")
        parsed = _parse_action(body)
        if isinstance(parsed, Response):
            return parsed
        action, method, to = parsed
        by = self.operator if action in ("start", "commit", "rollback") else None
        answers, errors = await run_in_threadpool(self.control.calibrate, device, action, method, to, by)
        if not answers:
            return error(502 if errors else 504, "; ".join(errors) or "no calibrator answered for this device")
        reply = answers[0]
        return JSONResponse(reply, status_code=200 if reply.get("ok") else 409)

    # ---------------------------------------------------------------------------------------------- stream
    async def stream(self, request: Request) -> Response:
        refused = self._view_refused(request)
        if refused:
            return refused
        device = request.query_params.get("device") or None
        if device is not None:
            known = self._known(device)
            if isinstance(known, Response):
                return known
        now = asyncio.get_running_loop().time()
        self.starting = [t for t in self.starting if now - t < STARTING_S]  # a stream never started: its place back
        if self.streams + len(self.starting) >= MAX_STREAMS:  # refused and closed: no lingering keep-alive
            refused = error(503, f"{MAX_STREAMS} event streams are open already: close a page or try again later")
            refused.headers["Connection"] = "close"
            return refused
        self.starting.append(now)
        return StreamingResponse(
            self._events(device),
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )

    async def _events(self, device: str | None) -> AsyncIterator[str | memoryview]:
        """The stream's events: the fleet's as ``FleetEvents`` made them (this stream only looks them up, so a
        thousand streams cost the loop no encoding), the device's detail every ``DETAIL_EVERY_S``; an ``event:
        closed`` with the reason when it cannot keep up."""
        reader, next_detail = Reader(), 0.0
        loop = asyncio.get_running_loop()
        self.streams += 1
        self.events.readers += 1
        if self.starting:
            self.starting.pop(0)
        if device:
            self.state.watch(device, +1)
        try:
            while not self.stopping.is_set():
                self.events.start(self.stopping)
                ticked = self.events.ticked  # the next tick's (taken before looking: none is missed)
                try:
                    texts, closing = self.events.take(reader)
                except Exception as exc:  # this stream ends (the page reconnects); the server goes on
                    self.guard.failed("http:stream", exc)
                    return
                if closing is not None:
                    self.state.dropped.count("stream:behind")
                    yield _event("closed", {"reason": closing})
                    return
                for text in texts:
                    for piece in pieces(text):  # each after the last drained (uvicorn's flow control)
                        yield piece
                if device and reader.version >= 0 and loop.time() >= next_detail:  # after its first fleet event
                    next_detail = loop.time() + DETAIL_EVERY_S
                    detail = self.guard.run("http:stream", self.state.detail, device)
                    yield _event("device", detail if detail is not None else {"device": device, "unknown": True})
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(ticked.wait(), max(1.0, 4 * self.interval_s))
        finally:
            self.streams -= 1
            self.events.readers -= 1
            if device:
                self.state.watch(device, -1)


async def _bounded_body(request: Request, limit: int) -> bytes | None:
    """The request's body, None when it declares or turns out longer than ``limit`` (not read past it)."""
    declared = request.headers.get("content-length", "")
    if declared and (not declared.isdigit() or int(declared) > limit):
        return None
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            return None
    return bytes(body)


_event = encode


def _parse_action(body: bytes) -> tuple[str, str | None, str | None] | Response:
    """(action, method, rollback target id) from a JSON body, or the 400 response saying what is wrong."""
    from magnet.calibration.choose import parse_choice

    try:
        data = loads_bounded(body or b"null", "body")
    except ValueError:
        return error(400, 'the body must be JSON: {"action": "start|status|commit|abort|rollback", "method": ...}')
    if not isinstance(data, dict):
        return error(400, 'the body must be a JSON object with an "action"')
    action, method = data.get("action"), data.get("method")
    if action not in ACTIONS:
        return error(400, f"action must be one of {', '.join(ACTIONS)}, got {action!r}")
    if method is not None:
        if not isinstance(method, str):
            return error(400, "method must be a string")
        try:
            method = parse_choice(method)
        except ValueError as exc:
            return error(400, str(exc))
    to = data.get("to")
    if to is not None and (action != "rollback" or not isinstance(to, str) or not CALIBRATION_ID.fullmatch(to)):
        return error(400, '"to" goes with rollback and must be a calibration id (8 to 64 hex digits)')
    return action, method, to


def create_app(
    state: FleetState,
    control: Control,
    token: str,
    view_needs_token: bool = False,
    interval_s: float = 0.25,
    operator: str = "",
    allowed_hosts: tuple[str, ...] = (),
) -> Starlette:
    """The ASGI app (``app.state.dashboard`` holds the handlers; set ``dashboard.stopping`` to end streams).
    ``operator``: who the page's commits and rollbacks are recorded as made by (``by``); ``allowed_hosts``: names a
    request's ``Host`` may give besides the loopback ones (``HostCheck``)."""
    dashboard = Dashboard(state, control, token, view_needs_token, interval_s, operator)
    guard = dashboard.guarded
    routes = [
        Route("/", guard("http:index", dashboard.index)),
        Route("/plotly.min.js", guard("http:plotly", dashboard.plotly)),
        Route("/api/fleet", guard("http:fleet", dashboard.fleet)),
        Route("/api/vehicles", guard("http:vehicles", dashboard.vehicles)),
        Route("/api/stream", guard("http:stream", dashboard.stream)),
        Route("/api/devices/{device}", guard("http:device", dashboard.device)),
        Route("/api/devices/{device}/history", guard("http:history", dashboard.history)),
        Route("/api/devices/{device}/calibrate", guard("http:calibrate", dashboard.calibrate), methods=["POST"]),
        Mount("/static", StaticFiles(directory=STATIC_DIR), name="static"),
    ]
    allowed = LOOPBACK_NAMES | {host_name(h) for h in allowed_hosts}
    app = Starlette(routes=routes, middleware=[Middleware(HostCheck, allowed=allowed)])
    app.state.dashboard = dashboard
    return app
