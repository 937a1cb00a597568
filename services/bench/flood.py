"""Hostile load for the flood test and ``magnet bench soak``, each run as its own process
(``python -m services.bench.flood KIND ...``, one JSON line on stdout at the end):

- ``ids``: ``--count`` raw messages of new device ids (``flood-<start+i>``, one 2-sample batch each) at up to
  ``--rate`` messages/s; congestion control BLOCK, so the transport loses none silently: every message sent reaches
  the subscriber, which must count it. Prints ``{"sent", "seconds", "rate"}``.
- ``bombs``: ``--count`` msgpack bombs of ``--size`` bytes (a 4-million-element array, as a peer could craft) on
  ``<prefix>/<device>/raw``. Prints ``{"sent", "bytes"}``.
- ``probe``: asks ``<prefix>/@status/<name>`` every ``--period`` s for ``--seconds`` s and prints ``{"asked",
  "answered", "latencies_s": [...], "worst_s", "last": last status}`` (a missing answer is a latency of None).

Loopback only: every session connects to ``tcp/127.0.0.1:<port>`` with multicast scouting off.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import msgpack
import numpy as np

from magnet import wire
from services.common.zenoh_session import ZenohSettings, open_session, payload_bytes


def _session(port: int) -> Any:
    return open_session(ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True))


def flood_messages(count: int, start: int = 0, prefix: str = wire.DEFAULT_PREFIX) -> list[tuple[str, bytes]]:
    """(key, payload) of ``count`` valid raw messages, each from a new device id ``flood-<start+i>``."""
    mag, acc = np.array([[20.0, 5.0, 40.0], [21.0, 5.0, 40.0]]), np.array([[0.0, 0.0, -9.8]] * 2)
    t_ns = np.array([1, 2], dtype=np.int64)
    out = []
    for i in range(start, start + count):
        device = f"flood-{i}"
        out.append(
            (wire.key(prefix, device, wire.Kind.RAW), wire.encode_raw(wire.RawBatch(device, 0, "sim", t_ns, mag, acc)))
        )
    return out


def flood_ids(port: int, count: int, rate: float, start: int = 0, prefix: str = wire.DEFAULT_PREFIX) -> dict[str, Any]:
    """Send the ``flood_messages`` at up to ``rate`` messages/s; the figures of the run."""
    import zenoh

    messages = flood_messages(count, start, prefix)
    block = zenoh.CongestionControl.BLOCK
    with _session(port) as session:
        publisher = session.declare_publisher(messages[0][0])
        deadline = time.monotonic() + 5.0
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        started = time.monotonic()
        for sent, (key, payload) in enumerate(messages):
            ahead = started + sent / rate - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
            session.put(key, payload, congestion_control=block)
        seconds = time.monotonic() - started
        time.sleep(0.5)  # let the last ones leave
        publisher.undeclare()
    return {"sent": count, "seconds": round(seconds, 3), "rate": round(count / max(seconds, 1e-9))}


def bomb(size: int) -> bytes:
    """A msgpack array of about ``size`` bytes of one-byte integers: small on the wire, millions of objects unpacked."""
    return msgpack.packb([0] * max(1, size - 5))


def send_bombs(port: int, count: int, size: int, device: str, prefix: str = wire.DEFAULT_PREFIX) -> dict[str, Any]:
    import zenoh

    payload = bomb(size)
    key = wire.key(prefix, device, wire.Kind.RAW)
    with _session(port) as session:
        time.sleep(1.0)  # routes to the subscribers
        for _ in range(count):
            session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(0.05)
        time.sleep(0.5)
    return {"sent": count, "bytes": len(payload)}


def probe(port: int, name: str, period_s: float, seconds: float, prefix: str = wire.DEFAULT_PREFIX) -> dict[str, Any]:
    """Ask the status of ``name`` every ``period_s`` for ``seconds``; latencies (s, None when unanswered)."""
    latencies: list[float | None] = []
    last: Any = None
    key = wire.status_key(prefix, name)
    with _session(port) as session:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            asked = time.monotonic()
            answer = None
            for reply in session.get(key, timeout=max(2.0, period_s)):
                if reply.ok is not None and answer is None:
                    answer = time.monotonic() - asked
                    last = wire.unpack(payload_bytes(reply.ok))
            latencies.append(answer)
            time.sleep(max(0.0, period_s - (time.monotonic() - asked)))
    answered = [x for x in latencies if x is not None]
    return {
        "asked": len(latencies),
        "answered": len(answered),
        "latencies_s": [None if x is None else round(x, 4) for x in latencies],
        "worst_s": round(max(answered), 4) if answered else None,
        "last": last,
    }


def rss_mb(pid: int) -> float | None:
    """Resident memory (MB) of process ``pid`` from /proc; None when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.bench.flood")
    parser.add_argument("kind", choices=("ids", "bombs", "probe"))
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--count", type=int, default=80_000)
    parser.add_argument("--rate", type=float, default=10_000.0)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--size", type=int, default=4_000_000)
    parser.add_argument("--device", default="bomb-1")
    parser.add_argument("--name", default="calibrator")
    parser.add_argument("--period", type=float, default=0.2)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args(argv)
    if args.kind == "ids":
        result = flood_ids(args.port, args.count, args.rate, args.start)
    elif args.kind == "bombs":
        result = send_bombs(args.port, args.count, args.size, args.device)
    else:
        result = probe(args.port, args.name, args.period, args.seconds)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
