"""The front of the Foxglove WebSocket (``magnet dashboard --foxglove HOST:PORT``): it reads each connection's HTTP
upgrade request, checks it, and only then splices the bytes to foxglove-sdk's own server, which listens on a private
loopback address (the SDK's server has no hook on the upgrade request's headers: it took any ``Origin`` and asked
for no token, so any web page in the operator's browser could read the live fleet; issue 32).

An upgrade is let through when:

- ``Host`` names a loopback name, the ``--foxglove`` host (unless a wildcard) or one given with ``--allow-host``
  (DNS rebinding), else 403;
- ``Origin``, when sent (browsers always send it), is ``http(s)://`` one of those names, any port; else 403. The
  Foxglove web app's page is ``https://app.foxglove.dev``: give ``--allow-host app.foxglove.dev`` to use it. A
  non-web origin (``null``, ``file://``: a desktop app's window loaded from files) passes only with the token;
- the token is given, else 401: the dashboard's control token in ``Authorization: Bearer``, ``X-Magnet-Token`` or
  as a WebSocket subprotocol ``magnet-token.TOKEN`` (headers a native client can send), or, for the Foxglove app,
  whose browser WebSocket can send nothing but its address, the *view token* in the address (``?token=VIEW``). The
  view token is derived from the control token (``view_token``) and opens only this socket: an address kept in the
  app's history, a log or a ``Referer`` never carries the token that controls calibrations.

Time and number are bounded: the request's head within ``HEAD_TIMEOUT_S`` and ``MAX_HEAD_BYTES``, at most
``MAX_WAITING`` connections waiting for their head (a new one past it closes the oldest) and ``MAX_CLIENTS``
spliced ones (503 past it). What is forwarded: the request line with the address's query removed, the headers
without the token ones (and without the subprotocol that carried it), then the bytes both ways.

The private address is 127.x.y.z with x, y, z random and a port the system chooses: a web page cannot find it by
scanning (about 2^38 addresses and ports), which it could on 127.0.0.1.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import secrets
from collections import OrderedDict
from urllib.parse import parse_qs, urlsplit

from services.common.loop_server import LoopServer
from services.dashboard.hosts import host_name

log = logging.getLogger("magnet.dashboard.foxglove")

HEAD_TIMEOUT_S = 5.0
MAX_HEAD_BYTES = 8192
MAX_WAITING = 64
MAX_CLIENTS = 32
TOKEN_PROTOCOL = "magnet-token."
#: origins of windows loaded from files (Electron apps' renderers): no site to check, so the token decides
NON_WEB_ORIGINS = frozenset({"null", "file://"})
_CHUNK = 65536


def view_token(token: str) -> str:
    """The token of the Foxglove socket's address: 22 characters derived from the control token (HMAC-SHA256), so
    it opens the socket and nothing else."""
    return hmac.new(token.encode(), b"magnet foxglove view", hashlib.sha256).hexdigest()[:22]


def private_loopback_host() -> str:
    """A random 127.x.y.z address (Linux answers the whole 127/8 on the loopback interface) for the SDK's server."""
    return f"127.{secrets.randbelow(254) + 1}.{secrets.randbelow(256)}.{secrets.randbelow(254) + 1}"


class Upgrade:
    """One parsed HTTP upgrade request: request line parts and headers (names lower case, values stripped)."""

    def __init__(self, head: bytes) -> None:
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        if len(parts) != 3 or parts[0] != "GET" or not parts[2].startswith("HTTP/1."):
            raise ValueError("not an HTTP/1.1 GET request")
        self.method, self.target, self.version = parts
        self.headers: list[tuple[str, str]] = []
        for line in lines[1:]:
            if line:
                name, sep, value = line.partition(":")
                if not sep or not name.strip():
                    raise ValueError("a malformed header line")
                self.headers.append((name.strip().lower(), value.strip()))

    def get(self, name: str) -> str | None:
        values = [v for n, v in self.headers if n == name]
        if len(values) > 1:
            raise ValueError(f"{name} given twice")
        return values[0] if values else None

    def protocols(self) -> list[str]:
        return [p.strip() for n, v in self.headers if n == "sec-websocket-protocol" for p in v.split(",") if p.strip()]


class FrontCheck:
    """The checks of an upgrade request (no sockets): ``refusal`` says why one is refused, ``forwarded`` what goes on
    to the SDK's server."""

    def __init__(self, token: str, allowed: frozenset[str]) -> None:
        if not token:
            raise ValueError("the Foxglove socket needs the dashboard's token")
        self.token, self.view, self.allowed = token, view_token(token), allowed

    def refusal(self, request: Upgrade) -> tuple[int, str] | None:
        """(HTTP status, reason) when ``request`` is refused, else None."""
        if (request.get("upgrade") or "").lower() != "websocket":
            return 400, "this address serves the Foxglove WebSocket protocol only (no Upgrade: websocket)"
        host = request.get("host") or ""
        if host_name(host) not in self.allowed:
            return 403, f"Host {host!r} is not one this dashboard answers to (give it with --allow-host)"
        origin = request.get("origin")
        token_ok = self._token_ok(request)
        if origin is not None and not self._origin_ok(origin, token_ok):
            return 403, f"connections from the web page at {origin!r} are refused (give its host with --allow-host)"
        if not token_ok:
            return 401, "the Foxglove socket needs the dashboard's token (its view token in the address: ?token=...)"
        return None

    def _origin_ok(self, origin: str, token_ok: bool) -> bool:
        """A web page's origin must name an allowed host; a non-web one (``null``, ``file://``: an app's window
        loaded from files, such as an Electron desktop app's, but also a sandboxed frame) only with the token."""
        if origin.strip().lower() in NON_WEB_ORIGINS:
            return token_ok
        parts = urlsplit(origin.lower())
        return parts.scheme in ("http", "https") and (parts.hostname or "") in self.allowed

    def _token_ok(self, request: Upgrade) -> bool:
        auth = request.get("authorization") or ""
        given = [auth[7:].strip()] if auth.lower().startswith("bearer ") else []
        given += [request.get("x-magnet-token") or ""]
        given += [p[len(TOKEN_PROTOCOL) :] for p in request.protocols() if p.startswith(TOKEN_PROTOCOL)]
        if any(g and hmac.compare_digest(g.encode(), self.token.encode()) for g in given):
            return True
        query = parse_qs(urlsplit(request.target).query).get("token", [])
        return any(hmac.compare_digest(q.encode(), self.view.encode()) for q in query)

    def forwarded(self, request: Upgrade) -> bytes:
        """The request as the SDK's server gets it: no query in the address, no token headers or subprotocol."""
        path = urlsplit(request.target).path or "/"
        lines = [f"GET {path} {request.version}"]
        for name, value in request.headers:
            if name in ("authorization", "x-magnet-token"):
                continue
            if name == "sec-websocket-protocol":
                value = ", ".join(p.strip() for p in value.split(",") if not p.strip().startswith(TOKEN_PROTOCOL))
                if not value:
                    continue
            lines.append(f"{name}: {value}")
        return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")


class FoxgloveFront(LoopServer):
    """Listens on ``host``:``port`` (0: a free one, ``self.port``) and splices checked upgrades to ``backend``
    (host, port), from a daemon thread of its own; ``close`` stops it."""

    def __init__(self, host: str, port: int, backend: tuple[str, int], check: FrontCheck) -> None:
        self.backend, self.check = backend, check
        self.waiting: OrderedDict[int, asyncio.StreamWriter] = OrderedDict()
        self.clients = 0
        self.refused: dict[int, int] = {}  # HTTP status -> refusals
        super().__init__(host, port, "foxglove-front", MAX_HEAD_BYTES)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        key = id(writer)
        while len(self.waiting) >= MAX_WAITING:
            self.waiting.popitem(last=False)[1].close()
        self.waiting[key] = writer
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
            self.waiting.pop(key, None)
            await self._handle(head, reader, writer)
        except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError):
            pass  # silent, too slow, too long or gone
        except Exception as exc:  # this connection ends, the front goes on
            log.warning("Foxglove connection failed: %s: %s", type(exc).__name__, exc)
        finally:
            self.waiting.pop(key, None)
            writer.close()

    async def _handle(self, head: bytes, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            request = Upgrade(head)
            refused = self.check.refusal(request)
        except ValueError as exc:
            refused = (400, f"a malformed upgrade request: {exc}")
        if refused is None and self.clients >= MAX_CLIENTS:
            refused = (503, f"{MAX_CLIENTS} Foxglove clients are connected already")
        if refused is not None:
            await self._refuse(writer, *refused)
            return
        back_reader, back_writer = await asyncio.wait_for(asyncio.open_connection(*self.backend), HEAD_TIMEOUT_S)
        self.clients += 1
        try:
            back_writer.write(self.check.forwarded(request))
            await asyncio.gather(_pipe(reader, back_writer), _pipe(back_reader, writer))
        finally:
            self.clients -= 1
            back_writer.close()

    async def _refuse(self, writer: asyncio.StreamWriter, status: int, reason: str) -> None:
        self.refused[status] = self.refused.get(status, 0) + 1
        text = {400: "Bad Request", 401: "Unauthorized", 403: "Forbidden", 503: "Service Unavailable"}[status]
        body = (reason + "\n").encode()
        writer.write(
            f"HTTP/1.1 {status} {text}\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: {len(body)}\r\n"
            f"Connection: close\r\n\r\n".encode()
            + body
        )
        with contextlib.suppress(TimeoutError, ConnectionError):
            await asyncio.wait_for(writer.drain(), HEAD_TIMEOUT_S)


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Copy ``reader`` to ``writer`` until either end closes; then close ``writer`` (the other direction ends too)."""
    try:
        while data := await reader.read(_CHUNK):
            writer.write(data)
            await writer.drain()
    except ConnectionError:
        pass
    finally:
        writer.close()
