"""The HTTP server of ``--metrics``: one thread, one asyncio loop, every connection bounded in time and in number.

prometheus-client's own ``start_http_server`` starts a thread per connection and waits for a request forever: idle
connections held open took a thread and a file each until the process's file limit, and then normal scrapes timed
out (issue 32). Here a connection costs a socket and a small task, never a thread:

- a request's head must arrive within ``HEAD_TIMEOUT_S`` and fit ``MAX_HEAD_BYTES``, its answer must be taken
  within ``WRITE_TIMEOUT_S``; then the connection is closed (one request per connection, ``Connection: close``);
- at most ``MAX_CONNECTIONS`` at once: a new one past it closes the oldest waiting connection, so a scraper always
  gets in however many idle ones are held open;
- the answer is made in the loop's thread (the families of a status map, milliseconds): no request waits for
  another's idle peer.

Only ``GET /metrics`` (and ``/``) is answered (404 else); the format follows ``Accept`` like prometheus-client's.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections import OrderedDict
from typing import Any

from services.common.loop_server import LoopServer

log = logging.getLogger("magnet.metrics")

HEAD_TIMEOUT_S = 5.0
WRITE_TIMEOUT_S = 5.0
MAX_HEAD_BYTES = 8192
MAX_CONNECTIONS = 64


class MetricsServer(LoopServer):
    """Serves ``registry`` (a prometheus-client ``CollectorRegistry``) at ``http://host:port/metrics`` from a daemon
    thread of its own; ``port`` 0 takes a free one (``self.port`` says which). ``close`` stops it."""

    def __init__(self, host: str, port: int, registry: Any, max_connections: int = MAX_CONNECTIONS) -> None:
        self.registry, self.max_connections = registry, max_connections
        self.open: OrderedDict[int, asyncio.StreamWriter] = OrderedDict()  # waiting connections, oldest first
        self.closed_oldest = 0  # connections closed to admit a newer one
        super().__init__(host, port, "metrics-http", MAX_HEAD_BYTES)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        key = id(writer)
        while len(self.open) >= self.max_connections:
            _, oldest = self.open.popitem(last=False)
            oldest.close()
            self.closed_oldest += 1
        self.open[key] = writer
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
            self.open.pop(key, None)  # answering now: no longer one to close for a newcomer
            writer.write(self._answer(head))
            await asyncio.wait_for(writer.drain(), WRITE_TIMEOUT_S)
        except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ConnectionError, ValueError):
            pass  # silent, too slow, too long or gone: closed below
        except Exception as exc:  # a failing collector: this connection ends, the server goes on
            log.warning("metrics request failed: %s", exc)
        finally:
            self.open.pop(key, None)
            writer.close()
            with contextlib.suppress(Exception):
                await asyncio.wait_for(writer.wait_closed(), 1.0)

    def _answer(self, head: bytes) -> bytes:
        from prometheus_client.exposition import choose_encoder

        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        path = parts[1].split("?", 1)[0] if len(parts) == 3 else ""
        if parts[0] != "GET" or path not in ("/metrics", "/"):
            return _response(404, "text/plain; charset=utf-8", b"only GET /metrics is served\n")
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
        encoder, content_type = choose_encoder(headers.get("accept", ""))
        return _response(200, content_type, encoder(self.registry))


def _response(status: int, content_type: str, body: bytes) -> bytes:
    reason = {200: "OK", 404: "Not Found"}[status]
    head = (
        f"HTTP/1.1 {status} {reason}\r\nContent-Type: {content_type}\r\nContent-Length: {len(body)}\r\n"
        "Connection: close\r\n\r\n"
    )
    return head.encode("latin-1") + body
