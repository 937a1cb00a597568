"""Hostile load for the flood test and ``magnet bench soak``, each run as its own process
(``python -m services.bench.flood KIND ...``, one JSON line on stdout at the end):

- ``ids``: ``--count`` raw messages of new device ids (``flood-<start+i>``, one 2-sample batch each) at up to
  ``--rate`` messages/s; congestion control BLOCK, so the transport loses none silently: every message sent reaches
  the subscriber, which must count it. Prints ``{"sent", "seconds", "rate"}``.
- ``bombs``: ``--count`` msgpack bombs of ``--size`` bytes (a 4-million-element array, as a peer could craft) on
  ``<prefix>/<device>/raw``. Prints ``{"sent", "bytes"}``.
- ``probe``: asks ``<prefix>/@status/<name>`` and every ``--key`` in turn, one every ``--period`` s, for
  ``--seconds`` s and prints ``{"asked", "answered", "worst_s": {key: s}, "latencies_s": {key: [...]}, "last": last
  status}`` (a missing answer is a latency of None).

Loopback only: every session connects to ``tcp/127.0.0.1:<port>`` with multicast scouting off.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import TYPE_CHECKING, Any

import msgpack
import numpy as np

from magnet import wire
from services.common.zenoh_session import ZenohSettings, matching, open_session, payload_bytes

if TYPE_CHECKING:
    import zenoh


def _session(port: int) -> zenoh.Session:
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
    with _session(port) as session, session.declare_publisher(messages[0][0]) as publisher:
        deadline = time.monotonic() + 5.0
        while not matching(publisher) and time.monotonic() < deadline:
            time.sleep(0.02)
        started = time.monotonic()
        for sent, (key, payload) in enumerate(messages):
            ahead = started + sent / rate - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)
            session.put(key, payload, congestion_control=block)
        seconds = time.monotonic() - started
        time.sleep(0.5)  # let the last ones leave
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


def probe(port: int, keys: list[str], period_s: float, seconds: float) -> dict[str, Any]:
    """Ask each of ``keys`` in turn, one every ``period_s``, for ``seconds``; per key the latencies (s, None when
    unanswered), and the last answer to the first key."""
    latencies: dict[str, list[float | None]] = {key: [] for key in keys}
    last: Any = None
    with _session(port) as session:
        end, turn = time.monotonic() + seconds, 0
        while time.monotonic() < end:
            key = keys[turn % len(keys)]
            turn += 1
            asked = time.monotonic()
            answer = None
            for reply in session.get(key, timeout=max(2.0, period_s)):
                if reply.ok is not None and answer is None:
                    answer = time.monotonic() - asked
                    if key == keys[0]:
                        last = wire.unpack(payload_bytes(reply.ok))
            latencies[key].append(answer)
            time.sleep(max(0.0, period_s - (time.monotonic() - asked)))
    answered = {key: [x for x in values if x is not None] for key, values in latencies.items()}
    return {
        "asked": sum(len(values) for values in latencies.values()),
        "answered": sum(len(values) for values in answered.values()),
        "worst_s": {key: round(max(values), 4) if values else None for key, values in answered.items()},
        "latencies_s": {key: [None if x is None else round(x, 4) for x in values] for key, values in latencies.items()},
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
    parser.add_argument("--name", default="calibrator", help="probe: the status of this service")
    parser.add_argument("--key", action="append", default=[], help="probe: another key to ask in turn (repeatable)")
    parser.add_argument("--period", type=float, default=0.2)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args(argv)
    if args.kind == "ids":
        result = flood_ids(args.port, args.count, args.rate, args.start)
    elif args.kind == "bombs":
        result = send_bombs(args.port, args.count, args.size, args.device)
    else:
        result = probe(
            args.port, [wire.status_key(wire.DEFAULT_PREFIX, args.name), *args.key], args.period, args.seconds
        )
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
