"""Two compass shards and two calibrator shards on loopback split a fleet of 1,000 emulated devices: every device's
headings are published exactly once (by the shard its id hashes to), and each calibrator shard collects and answers
only for its own devices."""

from __future__ import annotations

import json
import threading
from collections import Counter

import msgpack
import numpy as np
import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json, wait_for, wait_for_liveliness

from magnet.shard import shard_of

pytestmark = pytest.mark.integration

DEVICES = 1000
SECONDS = 4


def _status(service, port):
    code, lines = magnet_json("get", "status", service, *NO_SCOUT, *connect_args(port), "--timeout", "2", timeout=60)
    return lines[0] if code == 0 and lines else None


def _heading_subscriber(ports):
    """A session connected to the compasses that keeps the payload of every heading (callback: no loss)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in ports]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    got, lock = [], threading.Lock()

    def keep(sample):
        with lock:
            got.append(sample.payload.to_bytes())

    subscriber = session.declare_subscriber("magnet/*/heading", keep)
    # a compass that answers after the subscriber was declared on the same link has taken the declaration in
    wait_for(
        lambda: all(
            any(r.ok is not None for r in session.liveliness().get(f"magnet/@alive/compass/cmp{k}", timeout=1.0))
            for k in range(2)
        ),
        20,
        "the compasses to see the heading subscriber",
    )
    return session, subscriber, got


def test_two_shards_serve_a_fleet_of_1000_devices_exactly_once(procs, tmp_path):
    cal_ports, cmp_ports, edge_port = free_ports(2), free_ports(2), free_ports(1)[0]
    for k in range(2):
        procs.start(
            f"cal{k}",
            "calibrator",
            "--shard",
            f"{k}/2",
            "--name",
            f"cal{k}",
            "--no-auto",
            "--db",
            str(tmp_path / f"cal{k}.db"),
            *listen_args(cal_ports[k]),
        )
    for k in range(2):
        procs.start(
            f"cmp{k}",
            "compass",
            "--shard",
            f"{k}/2",
            "--name",
            f"cmp{k}",
            *listen_args(cmp_ports[k]),
            *connect_args(*cal_ports),
        )
    for k in range(2):  # peers do not forward for each other: each asked at its own port
        wait_for_liveliness(cal_ports[k], {f"magnet/@alive/calibrator/cal{k}"})
        wait_for_liveliness(cmp_ports[k], {f"magnet/@alive/compass/cmp{k}"})
    session, subscriber, got = _heading_subscriber(cmp_ports)
    try:
        edge = procs.start(
            "edge",
            "edge",
            "--emulate",
            "--devices",
            str(DEVICES),
            "--device",
            "f",
            "--rate",
            "10",
            "--batch",
            "10",
            "--duration",
            str(SECONDS),
            *listen_args(edge_port),
            *connect_args(*cmp_ports, *cal_ports),
        )
        edge.wait(timeout=60)
        published = json.loads(procs.log("edge").strip().splitlines()[-1])["published_batches"]

        def settled():
            statuses = [_status(f"cmp{k}", cmp_ports[k]) for k in range(2)]
            if all(statuses) and sum(s["published_batches"] for s in statuses) == len(got) > 0:
                return statuses
            return None

        compasses = wait_for(settled, 30, "every heading the compasses published")
    finally:
        subscriber.undeclare()
        session.close()

    messages = [msgpack.unpackb(payload) for payload in got]
    seen = Counter((m["device"], m["seq"]) for m in messages)
    assert max(seen.values()) == 1, "a batch published by both shards"
    devices = {device for device, _ in seen}
    assert devices == {f"f-{i:03d}" for i in range(DEVICES)}, f"{DEVICES - len(devices)} devices never served"
    assert len(messages) >= 0.95 * published
    by_shard = Counter(shard_of(m["device"], 2) for m in messages)
    assert [s["shard"] for s in compasses] == ["0/2", "1/2"]
    assert [s["published_batches"] for s in compasses] == [by_shard[0], by_shard[1]]
    assert min(by_shard.values()) > 0.4 * len(messages)

    calibrators = [_status(f"cal{k}", cal_ports[k]) for k in range(2)]
    received = sum(s["received_batches"] for s in calibrators)
    assert 0.9 * published <= received <= published  # each batch collected by one shard at most
    assert min(s["received_batches"] for s in calibrators) > 0.4 * published
    for device in ("f-000", "f-001", "f-002", "f-003"):
        code, replies = magnet_json(
            "calibrate", device, "status", *NO_SCOUT, *connect_args(*cal_ports), "--timeout", "2", timeout=60
        )
        assert code == 0 and len(replies) == 1 and replies[0]["device"] == device
    np.testing.assert_array_equal(sorted(by_shard), [0, 1])
