"""Many event streams against a running dashboard, for ``magnet bench soak`` and the tests (issue 32: 2,000 streams
took 73 % CPU; under a 1,024-file limit 1,100 gave 2,479 tracebacks). Run as its own process,
``python -m services.bench.stream_flood --port HTTP_PORT --count 2000 --seconds 20 [--no-read] [--token T]
[--rate 200]``, it
prints one JSON line at the end (``hold_streams``'s figures).

Each connection asks ``GET /api/stream`` on 127.0.0.1 and is then held open for ``seconds``: read as a page would
(default) or never read (``--no-read``: slow clients, which the dashboard should cut off). Meanwhile ``/api/fleet``
is asked once a second on a connection of its own, and the slowest answer is reported: what a real page would wait.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import resource
import selectors
import socket
import time
import urllib.request
from typing import Any

log = logging.getLogger("magnet.bench")
REQUEST = "GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{auth}\r\n"


def _raise_file_limit(wanted: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(resource.RLIMIT_NOFILE, (min(wanted, hard), hard))


def _fleet_seconds(port: int, token: str) -> float | None:
    """Seconds ``/api/fleet`` took to answer (None: no answer within 5 s)."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    started = time.monotonic()
    try:
        with urllib.request.urlopen(
            urllib.request.Request(f"http://127.0.0.1:{port}/api/fleet", headers=headers), timeout=5
        ) as reply:
            reply.read()
    except OSError as exc:
        log.info("/api/fleet unanswered: %s", exc)
        return None
    return time.monotonic() - started


def hold_streams(
    port: int, count: int, seconds: float, token: str = "", read: bool = True, rate: float = 200.0
) -> dict[str, Any]:
    """Open ``count`` event streams to the dashboard at 127.0.0.1:``port``, ``rate`` a second (pages reconnecting,
    not one burst: uvicorn answers 503 to every request while more than its connection limit are open), and hold
    them ``seconds``; figures:
    ``opened`` (connected), ``streaming`` (answered 200), ``refused`` (by status, e.g. 503), ``closed_by_server``
    (while held), ``bytes`` read, ``fleet_worst_s`` / ``fleet_unanswered`` (``/api/fleet`` asked once a second)."""
    _raise_file_limit(count + 64)
    request = REQUEST.format(port=port, auth=f"Authorization: Bearer {token}\r\n" if token else "").encode()
    selector = selectors.DefaultSelector()
    heads: dict[socket.socket, bytes] = {}
    figures: dict[str, Any] = {"opened": 0, "streaming": 0, "refused": {}, "closed_by_server": 0, "bytes": 0}
    opening = time.monotonic()
    for i in range(count):
        time.sleep(max(0.0, opening + i / rate - time.monotonic()))
        try:
            sock = socket.socket()
            if not read:  # a small window, as a stalled client's
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sock.settimeout(5)
            sock.connect(("127.0.0.1", port))
            sock.sendall(request)
        except OSError:
            continue
        sock.setblocking(False)
        figures["opened"] += 1
        heads[sock] = b""
        selector.register(sock, selectors.EVENT_READ)
    worst, unanswered, next_probe = 0.0, 0, time.monotonic()
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if time.monotonic() >= next_probe:
            next_probe += 1.0
            took = _fleet_seconds(port, token)
            worst, unanswered = (worst, unanswered + 1) if took is None else (max(worst, took), unanswered)
        for key, _ in selector.select(timeout=0.2 if read else 0.0):
            _take(key.fileobj, selector, heads, figures, read)  # type: ignore[arg-type]
        if not read:
            time.sleep(0.2)
    if not read:
        figures["closed_by_server"] = sum(_closed(sock) for sock in heads)
    for sock in heads:
        sock.close()
    selector.close()
    return figures | {"fleet_worst_s": round(worst, 3), "fleet_unanswered": unanswered}


def _closed(sock: socket.socket) -> bool:
    """Whether the server closed ``sock`` (what it sent before is read and dropped)."""
    try:
        while sock.recv(1 << 20):
            pass
    except (BlockingIOError, InterruptedError):
        return False
    except OSError:
        return True
    return True


def _take(
    sock: socket.socket, selector: selectors.BaseSelector, heads: dict[socket.socket, bytes], figures: dict, read: bool
) -> None:
    """Read what ``sock`` has (its status line first; with ``read`` False only that)."""
    try:
        data = sock.recv(65536)
    except (BlockingIOError, InterruptedError):
        return
    except OSError:
        data = b""
    if b"\r\n" not in heads[sock]:
        heads[sock] += data
        if b"\r\n" in heads[sock]:
            status = heads[sock].split(b" ", 2)[1].decode(errors="replace") if b" " in heads[sock] else "?"
            if status == "200":
                figures["streaming"] += 1
            else:
                figures["refused"][status] = figures["refused"].get(status, 0) + 1
    figures["bytes"] += len(data)
    if not data:
        selector.unregister(sock)
        figures["closed_by_server"] += 1
    elif not read and b"\r\n" in heads[sock]:
        selector.unregister(sock)  # its status is known: from now on it reads nothing (a slow client)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.bench.stream_flood")
    parser.add_argument("--port", type=int, required=True, help="the dashboard's HTTP port on 127.0.0.1")
    parser.add_argument("--count", type=int, default=2000)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--token", default="")
    parser.add_argument("--no-read", action="store_true", help="never read the streams (slow clients)")
    parser.add_argument("--rate", type=float, default=200.0, help="connections opened a second")
    args = parser.parse_args(argv)
    figures = hold_streams(args.port, args.count, args.seconds, args.token, read=not args.no_read, rate=args.rate)
    print(json.dumps(figures), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
