"""Which hosts and origins the dashboard answers (``HostCheck``): a web page elsewhere cannot read the fleet through
the operator's browser, even by DNS rebinding (issue 32)."""

from __future__ import annotations

from typing import Any

from starlette.responses import JSONResponse

#: names a request's Host may always give
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def host_name(value: str) -> str:
    """The host name of a ``Host`` header value (``name``, ``name:port``, ``[v6]:port``), lower case."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else value
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


class HostCheck:
    """ASGI middleware: 403 for a request whose ``Host`` is not one of ``allowed`` names (DNS rebinding), or whose
    ``Origin`` is not the page's own (``http(s)://`` + the same ``Host``)."""

    def __init__(self, app: Any, allowed: frozenset[str]) -> None:
        self.app, self.allowed = app, allowed

    def refusal(self, headers: dict[bytes, bytes]) -> str | None:
        host = headers.get(b"host", b"").decode("latin-1")
        if host_name(host) not in self.allowed:
            return f"Host {host!r} is not one this dashboard answers to (give it with --allow-host)"
        origin = headers.get(b"origin")
        if origin is not None:
            text = origin.decode("latin-1").lower()
            if text not in (f"http://{host.lower()}", f"https://{host.lower()}"):
                return f"requests from the web page at {text!r} are refused: open the dashboard's own page"
        return None

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket"):
            refused = self.refusal(dict(scope.get("headers") or ()))
            if refused is not None:
                if scope["type"] == "websocket":
                    await send({"type": "websocket.close", "code": 1008})
                    return
                await JSONResponse({"error": refused}, status_code=403)(scope, receive, send)
                return
        await self.app(scope, receive, send)
