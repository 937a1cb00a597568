"""Hostile loads of the front door for ``magnet bench soak``, each run as its own process
(``python -m services.bench.front_loads KIND ...``, one JSON line on stdout at the end):

- ``mavlink``: ``--count`` HIGHRES_IMU messages to a MAVLink UDP port (``udpin`` of an edge), each from another
  system id (1..255) and ``id`` (0..255), at up to ``--rate`` messages/s: the flood of device ids one port made
  (issue 32). Prints ``{"sent", "seconds"}``.
- ``vehicle``: one real vehicle (system id ``--sysid``, compass SCALED_IMU2) turning slowly at 20 Hz for
  ``--seconds``, to the same port: the device the flood must not affect. Prints ``{"sent"}``.
- ``streams``: ``--count`` dashboard event streams (``GET /api/stream``) opened at once on ``--http HOST:PORT``,
  held ``--seconds``, then closed. Prints ``{"opened", "answered": {status: n}, "refused"}``: a status is the HTTP
  code (``503:connections`` uvicorn's limit of connections, ``503:streams`` the app's limit of event streams), or
  ``none`` for a connection closed without an answer, ``silent`` for one that got neither a byte nor a close
  within ``--seconds`` and ``--grace`` more (``late``: answered in the grace, counted by status too); ``refused``
  counts connections that could not be made.

Loopback only.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import resource
import selectors
import socket
import sys
import time
from typing import Any, cast

from pymavlink.dialects.v20 import common as mav


def _udp(port: int) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(("127.0.0.1", port))
    return sock


def mavlink_flood(port: int, count: int, rate: float) -> dict[str, Any]:
    """HIGHRES_IMU from ``count`` (system id, id) pairs, one message each."""
    sock, started = _udp(port), time.monotonic()
    for k in range(count):
        sysid, imu_id = 2 + k % 254, (k // 254) % 256
        link = mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
        msg = mav.MAVLink_highres_imu_message(k * 20_000, 0, 0, -9.8, 0, 0, 0, 0.2, 0.05, 0.4, 0, 0, 0, 20, 0, imu_id)
        with contextlib.suppress(OSError):  # nobody listening for a moment (the edge restarting): sent anyway
            sock.send(msg.pack(link))
        ahead = started + (k + 1) / rate - time.monotonic()
        if ahead > 0:
            time.sleep(ahead)
    sock.close()
    return {"sent": count, "seconds": round(time.monotonic() - started, 3)}


def vehicle(port: int, sysid: int, seconds: float) -> dict[str, Any]:
    """One vehicle's compass (SCALED_IMU2, milligauss) turning 3 deg a message, at 20 Hz."""
    sock, link = _udp(port), mav.MAVLink(None, srcSystem=sysid, srcComponent=1)
    started, sent = time.monotonic(), 0
    while (now := time.monotonic()) < started + seconds:
        angle = math.radians(3.0 * sent)
        field = (int(400 * math.cos(angle)), int(400 * math.sin(angle)), 100)
        msg = mav.MAVLink_scaled_imu2_message(int((now - started) * 1000), 0, 0, -1000, 0, 0, 0, *field)
        with contextlib.suppress(OSError):
            sock.send(msg.pack(link))
        sent += 1
        time.sleep(max(0.0, started + sent * 0.05 - time.monotonic()))
    sock.close()
    return {"sent": sent}


def streams(http: str, count: int, seconds: float, grace: float = 10.0) -> dict[str, Any]:
    """``count`` event streams at once; what the dashboard answered each (HTTP status), held ``seconds``; a
    connection with no answer yet at the end of the hold is waited for ``grace`` s more (its answer counted, and in
    ``late``: slow, not lost) while the others are closed."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, min(hard, count + 256)), hard))
    host, port = http.rsplit(":", 1)
    request = f"GET /api/stream HTTP/1.1\r\nHost: {http}\r\nAccept: text/event-stream\r\n\r\n".encode()
    selector, opened, refused = selectors.DefaultSelector(), [], 0
    for _ in range(count):
        try:
            sock = socket.create_connection((host, int(port)), timeout=2.0)
            sock.sendall(request)
            sock.setblocking(False)
        except OSError:
            refused += 1
            continue
        opened.append(sock)
        selector.register(sock, selectors.EVENT_READ)
    answered: dict[str, int] = {}
    first: dict[int, bytes] = {}
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        for key, _ in selector.select(timeout=min(left, 0.5)):
            _read_answer(cast(socket.socket, key.fileobj), selector, first, answered)
    late = _late_answers(opened, selector, first, answered, grace)
    silent = len(opened) - len(first)  # neither a byte nor a close within the hold and the grace
    if silent:
        answered["silent"] = silent
    return {"opened": len(opened), "answered": answered, "refused": refused, "late": late, "grace_s": grace}


def _late_answers(
    opened: list[socket.socket],
    selector: selectors.BaseSelector,
    first: dict[int, bytes],
    answered: dict[str, int],
    grace: float,
) -> int:
    """Close the answered connections and wait up to ``grace`` s for the first bytes of the others; how many came."""
    waiting, late = [sock for sock in opened if sock.fileno() not in first], 0
    for sock in opened:
        if sock.fileno() in first:
            with contextlib.suppress(KeyError, ValueError):
                selector.unregister(sock)
            sock.close()
    end = time.monotonic() + grace
    while (left := end - time.monotonic()) > 0 and len(first) < len(opened):
        for key, _ in selector.select(timeout=min(left, 0.5)):
            sock = cast(socket.socket, key.fileobj)
            late += sock.fileno() not in first
            _read_answer(sock, selector, first, answered)
            with contextlib.suppress(KeyError, ValueError):
                selector.unregister(sock)
    for sock in waiting:
        sock.close()
    return late


def _read_answer(
    sock: socket.socket, selector: selectors.BaseSelector, first: dict[int, bytes], answered: dict[str, int]
) -> None:
    """Read what ``sock`` has; its first bytes give its answer (counted in ``answered`` by status)."""
    try:
        data = sock.recv(65536)
    except OSError:
        data = b""
    if sock.fileno() not in first:
        first[sock.fileno()] = data
        status = data.split(b" ", 2)[1].decode(errors="replace") if data.startswith(b"HTTP/") else "none"
        if status == "503":  # whose refusal: uvicorn's connection limit, or the app's limit of streams
            status += ":connections" if b"Service Unavailable" in data else ":streams"
        answered[status] = answered.get(status, 0) + 1
    if not data:
        with contextlib.suppress(KeyError, ValueError):
            selector.unregister(sock)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.bench.front_loads")
    parser.add_argument("kind", choices=("mavlink", "vehicle", "streams"))
    parser.add_argument("--port", type=int, default=0, help="mavlink, vehicle: the edge's UDP port")
    parser.add_argument("--http", default="127.0.0.1:8080", help="streams: the dashboard's HOST:PORT")
    parser.add_argument("--count", type=int, default=20_000)
    parser.add_argument("--rate", type=float, default=5_000.0)
    parser.add_argument("--sysid", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=8.0)
    parser.add_argument("--grace", type=float, default=10.0, help="streams: wait this long more for unanswered ones")
    args = parser.parse_args(argv)
    if args.kind == "mavlink":
        result = mavlink_flood(args.port, args.count, args.rate)
    elif args.kind == "vehicle":
        result = vehicle(args.port, args.sysid, args.seconds)
    else:
        result = streams(args.http, args.count, args.seconds, args.grace)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
