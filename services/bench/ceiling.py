"""Zenoh's own rate on this machine, for ``magnet bench pipeline``: a publisher process that puts ready-made raw
payloads (the edge's messages: same devices, batch, gyroscope and truth, wire v 2) as fast as it can, and a subscriber
in the measuring process that only counts them. No decoding, no processing: the ceiling the pipeline is held to.

The publisher runs as ``python -m services.bench.ceiling PORT DEVICES BATCH SECONDS GYRO`` and prints one JSON line.

``generate`` (``python -m services.bench.ceiling generate PORTS DEVICES RATE BATCH SECONDS GYRO``) is the pipeline
benchmark's load: the edge's messages for a simulated fleet, simulated once ahead (``SimulatedDevices`` costs about
1.3 us per sample with gyroscopes, as much as the whole compass) and then, paced at the rate, each stamped afresh
(``t_ns`` ending now, ``seq``) and encoded per message like the edge's. It prints the edge's summary line.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import threading
import time
from typing import TYPE_CHECKING, Any

import msgpack
import numpy as np

from magnet import wire
from magnet.simulator import SimulatedDevices
from services.common.zenoh_session import free_ports, matching

if TYPE_CHECKING:
    import zenoh

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
        return (
            f"zenoh ceiling, batch {self.batch} ({self.payload_bytes:,} B messages, no processing): "
            f"{self.message_rate:,.0f} messages/s = {self.sample_rate:,.0f} samples/s received "
            f"({self.published / self.seconds:,.0f} messages/s put); load average {os.getloadavg()[0]:.1f}"
        )


def payloads(devices: int, batch: int, gyro: bool) -> list[tuple[str, bytes]]:
    """(key, payload) of the edge's raw messages for ``devices`` simulated devices, a few batches each."""
    fleet = SimulatedDevices(n_devices=devices, rate_hz=100.0, seed=1, gyro=gyro)
    out = []
    for seq in range(max(1, -(-DISTINCT_PAYLOADS // devices))):
        step = fleet.step(batch)
        for d in range(devices):
            truth = {"heading_deg": step.heading_deg[d], "pitch_deg": step.pitch_deg[d], "roll_deg": step.roll_deg[d]}
            batch_d = wire.RawBatch(
                f"c-{d:03d}",
                seq,
                "sim",
                step.t_ns,
                step.mag_ut[d],
                step.acc_ms2[d],
                truth,
                None if step.gyr_rads is None else step.gyr_rads[d],
            )
            out.append((wire.key("magnet", batch_d.device, wire.Kind.RAW), wire.encode_raw(batch_d)))
    return out


def publish(port: int, devices: int, batch: int, seconds: float, gyro: bool) -> dict[str, Any]:
    """Put the payloads round and round for ``seconds`` (blocking congestion control, as the edge)."""
    import zenoh

    items = payloads(devices, batch, gyro)
    conf = zenoh.Config()
    for key, value in {"listen/endpoints": [f"tcp/127.0.0.1:{port}"], "scouting/multicast/enabled": False}.items():
        conf.insert_json5(key, json.dumps(value))
    with zenoh.open(conf) as session, session.declare_publisher(items[0][0]) as first:
        deadline = time.monotonic() + 10
        while not matching(first) and time.monotonic() < deadline:
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

    def count(_sample: zenoh.Sample) -> None:
        with lock:
            counted[0] += 1

    publisher = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.bench.ceiling",
            str(port),
            str(devices),
            str(batch),
            str(seconds),
            str(int(gyro)),
        ],
        stdout=subprocess.PIPE,
        text=True,
        stdin=subprocess.DEVNULL,
    )
    try:
        with _open_when_listening(conf) as session, session.declare_subscriber("magnet/*/raw", count):
            out, _ = publisher.communicate(timeout=seconds + 120)
    finally:
        if publisher.poll() is None:
            publisher.kill()
    result = json.loads(out.strip().splitlines()[-1])
    return Ceiling(batch, result["payload_bytes"], result["published"], counted[0], result["seconds"])


def device_name(d: int) -> str:
    """The id of the load's device number ``d``."""
    return f"b-{d:03d}"


def _fleet_batches(devices: int, batch: int, gyro: bool, steps: int) -> list[list[wire.RawBatch]]:
    fleet = SimulatedDevices(n_devices=devices, rate_hz=100.0, seed=1, gyro=gyro)
    out = []
    for _ in range(steps):
        step = fleet.step(batch)
        out.append(
            [
                wire.RawBatch(
                    device_name(d),
                    0,
                    "sim",
                    step.t_ns,
                    step.mag_ut[d],
                    step.acc_ms2[d],
                    {"heading_deg": step.heading_deg[d], "pitch_deg": step.pitch_deg[d], "roll_deg": step.roll_deg[d]},
                    None if step.gyr_rads is None else step.gyr_rads[d],
                )
                for d in range(devices)
            ]
        )
    return out


class _Stamper:
    """The edge's v 2 message of one batch with a new ``seq`` and ``t_ns``, without encoding it again: the bytes
    before ``seq``, between ``seq`` and the ``t_ns`` data and after it are cut once from ``wire.encode_raw`` (the
    message's map keeps its order: v, device, seq, sensor, t_ns, ...), so that the load costs a few us per message
    and leaves the CPU to the pipeline it measures. ``stamp`` gives the bytes ``wire.encode_raw`` would."""

    def __init__(self, batch: wire.RawBatch) -> None:
        self.n = len(batch)
        marker = np.arange(1, self.n + 1, dtype="<i8") * 0x0101010101010101  # bytes no float or header holds
        template = wire.encode_raw(dataclasses.replace(batch, seq=0, t_ns=marker))
        seq_at = template.index(msgpack.packb("seq")) + len(msgpack.packb("seq"))
        data_at = template.index(marker.tobytes())
        self.head, self.middle = template[:seq_at], template[seq_at + 1 : data_at]  # seq 0 packs as one byte
        self.tail = template[data_at + 8 * self.n :]

    def stamp(self, seq: int, t_ns: np.ndarray) -> bytes:
        return b"".join((self.head, msgpack.packb(seq), self.middle, t_ns.astype("<i8").tobytes(), self.tail))


def generate(ports: list[int], devices: int, rate: float, batch: int, seconds: float, gyro: bool) -> dict[str, Any]:
    """Put every device's batch each ``batch / rate`` s, spread over the period, stamped when it goes out."""
    import zenoh

    steps = [[_Stamper(b) for b in step] for step in _fleet_batches(devices, batch, gyro, 4)]
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in ports]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    sample_ns, gap = int(1e9 / rate), batch / rate / devices
    offsets = sample_ns * np.arange(batch - 1, -1, -1, dtype=np.int64)
    keys = [wire.key("magnet", device_name(d), wire.Kind.RAW) for d in range(devices)]
    with zenoh.open(conf) as session:
        block, put, sent = zenoh.CongestionControl.BLOCK, session.put, 0
        start = time.monotonic()
        while (now := time.monotonic()) < start + seconds:
            k, d = divmod(sent, devices)
            delay = start + sent * gap - now
            if delay > 0.001:
                time.sleep(delay)
            put(keys[d], steps[k % len(steps)][d].stamp(k, time.time_ns() - offsets), congestion_control=block)
            sent += 1
        elapsed = time.monotonic() - start
        time.sleep(0.3)
    return {"devices": devices, "published_samples": sent * batch, "published_batches": sent, "seconds": elapsed}


def _open_when_listening(conf: zenoh.Config) -> zenoh.Session:
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
    if sys.argv[1] == "generate":
        _ports, _devices, _rate, _batch, _seconds, _gyro = sys.argv[2:8]
        print(
            json.dumps(
                generate(
                    [int(p) for p in _ports.split(",")],
                    int(_devices),
                    float(_rate),
                    int(_batch),
                    float(_seconds),
                    _gyro == "1",
                )
            ),
            flush=True,
        )
    else:
        _port, _devices, _batch, _seconds, _gyro = sys.argv[1:6]
        print(json.dumps(publish(int(_port), int(_devices), int(_batch), float(_seconds), _gyro == "1")), flush=True)
