"""Zenoh's own rate on this machine, for ``magnet bench pipeline``: a publisher process that puts ready-made raw
payloads (the edge's messages: same devices, batch, gyroscope and truth, wire v 2) as fast as it can, and a subscriber
in the measuring process that only counts them. No decoding, no processing: the ceiling the pipeline is held to.

The publisher runs as ``python -m services.bench.ceiling PORT DEVICES BATCH SECONDS GYRO`` and prints one JSON line.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import threading
import time
from typing import Any

from magnet import wire
from magnet.simulator import FleetSimulator
from services.common.zenoh_session import free_ports

DISTINCT_PAYLOADS = 2000  # at least this many different messages cycled through


@dataclasses.dataclass(frozen=True)
class Ceiling:
    """What the subscriber counted: messages and samples per second, and the payload size (bytes)."""

    batch: int
    payload_bytes: int
    published: int
    received: int
    seconds: float

    @property
    def message_rate(self) -> float:
        return self.received / self.seconds

    @property
    def sample_rate(self) -> float:
        return self.message_rate * self.batch

    def line(self) -> str:
        return (f"zenoh ceiling, batch {self.batch} ({self.payload_bytes:,} B messages, no processing): "
                f"{self.message_rate:,.0f} messages/s = {self.sample_rate:,.0f} samples/s received "
                f"({self.published / self.seconds:,.0f} messages/s put)")


def payloads(devices: int, batch: int, gyro: bool) -> list[tuple[str, bytes]]:
    """(key, payload) of the edge's raw messages for ``devices`` simulated devices, a few batches each."""
    fleet = FleetSimulator(n_devices=devices, rate_hz=100.0, seed=1, gyro=gyro)
    out = []
    for seq in range(max(1, -(-DISTINCT_PAYLOADS // devices))):
        step = fleet.step(batch)
        for d in range(devices):
            truth = {"heading_deg": step.heading_deg[d], "pitch_deg": step.pitch_deg[d], "roll_deg": step.roll_deg[d]}
            batch_d = wire.RawBatch(f"c-{d:03d}", seq, "sim", step.t_ns, step.mag_ut[d], step.acc_ms2[d], truth,
                                    None if step.gyr_rads is None else step.gyr_rads[d])
            out.append((wire.key("magnet", batch_d.device, wire.Kind.RAW), wire.encode_raw(batch_d)))
    return out


def publish(port: int, devices: int, batch: int, seconds: float, gyro: bool) -> dict[str, Any]:
    """Put the payloads round and round for ``seconds`` (blocking congestion control, as the edge)."""
    import zenoh

    items = payloads(devices, batch, gyro)
    conf = zenoh.Config()
    for key, value in {"listen/endpoints": [f"tcp/127.0.0.1:{port}"], "scouting/multicast/enabled": False}.items():
        conf.insert_json5(key, json.dumps(value))
    with zenoh.open(conf) as session:
        first = session.declare_publisher(items[0][0])
        deadline = time.monotonic() + 10
        while not first.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        block, put, count = zenoh.CongestionControl.BLOCK, session.put, 0
        start = time.monotonic()
        end = start + seconds
        while time.monotonic() < end:
            for key, payload in items:
                put(key, payload, congestion_control=block)
            count += len(items)
        elapsed = time.monotonic() - start
        time.sleep(0.3)
    return {"published": count, "seconds": elapsed, "payload_bytes": len(items[0][1])}


def measure(devices: int, batch: int, seconds: float, gyro: bool) -> Ceiling:
    """Start the publisher process, count what arrives in a callback here, return the rates."""
    import zenoh

    port = free_ports(1)[0]
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    counted, lock = [0], threading.Lock()

    def count(_sample: Any) -> None:
        with lock:
            counted[0] += 1

    publisher = subprocess.Popen([sys.executable, "-m", "services.bench.ceiling", str(port), str(devices), str(batch),
                                  str(seconds), str(int(gyro))], stdout=subprocess.PIPE, text=True,
                                 stdin=subprocess.DEVNULL)
    try:
        with _open_when_listening(conf) as session:
            session.declare_subscriber("magnet/*/raw", count)
            out, _ = publisher.communicate(timeout=seconds + 120)
    finally:
        if publisher.poll() is None:
            publisher.kill()
    result = json.loads(out.strip().splitlines()[-1])
    return Ceiling(batch, result["payload_bytes"], result["published"], counted[0], result["seconds"])


def _open_when_listening(conf: Any) -> Any:
    import zenoh

    deadline = time.monotonic() + 20
    while True:
        try:
            return zenoh.open(conf)
        except Exception:  # the publisher is not listening yet
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


if __name__ == "__main__":
    _port, _devices, _batch, _seconds, _gyro = sys.argv[1:6]
    print(json.dumps(publish(int(_port), int(_devices), int(_batch), float(_seconds), _gyro == "1")), flush=True)
