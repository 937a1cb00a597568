"""A hostile peer on loopback against a signing calibrator and a trusting compass: forged and absurd calibrations,
absurd query parameters. The services stay up, the genuine calibration stays in force, headings keep flowing."""

from __future__ import annotations

import subprocess
import sys

import pytest
from helpers import NO_SCOUT, connect_args, emulated_edge, free_ports, listen_args, magnet_json, run_magnet, wait_for

pytestmark = pytest.mark.integration

DEVICE = "hp-1"

#: a plain Zenoh peer that puts forged calibrations (argv: port, the genuine record as JSON, another key's file)
FORGER = r"""
import json, sys, msgpack, zenoh
from magnet import signing
port, genuine, other_key = int(sys.argv[1]), json.loads(sys.argv[2]), sys.argv[3]
other = signing.Signer(signing.load_private_key(open(other_key, "rb").read()))
ours = {k: v for k, v in genuine.items() if k not in ("sig", "key_id")}
moved = {**ours, "offset": [100.0, 0.0, 0.0], "created_ns": ours["created_ns"] + 1}
forged = [
    other.sign(moved),                                        # signed by a key the compass does not trust
    moved,                                                    # unsigned
    {**genuine, "offset": [100.0, 0.0, 0.0]},                 # the genuine signature on changed coefficients
    other.sign({**moved, "accepted": False}),                 # a rejected fit
    {**genuine, "matrix": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]]},  # a reflection
    {**genuine, "matrix": [[1e9, 0, 0], [0, 1e9, 0], [0, 0, 1e9]]},  # a 1e9 scale
    {"v": 1, "device": "%s", "offset": [100, 0, 0], "matrix": [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], "accepted": False},
]
conf = zenoh.Config()
conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
conf.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(conf) as session:
    publisher = session.declare_publisher("magnet/%s/calibration")
    import time
    deadline = time.monotonic() + 10
    while not publisher.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.02)
    for record in forged + forged:  # twice: the count needs only one of each to arrive
        publisher.put(msgpack.packb(record))
    for limit in ("99999999999999999999999999", "-5", "lots", "1e400"):
        list(session.get(f"magnet/%s/calibration/history?limit={limit}", timeout=2))
    print(len(forged))
""" % (DEVICE, DEVICE, DEVICE)  # noqa: UP031 (str.format would need every brace of the script doubled)

#: 8,000 new device ids in a burst, one small raw batch each (argv: ports)
FLOOD = r"""
import json, sys, time, numpy as np, zenoh
from magnet import wire
conf = zenoh.Config()
conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in sys.argv[1:]]))
conf.insert_json5("scouting/multicast/enabled", "false")
rng = np.random.default_rng(7)
with zenoh.open(conf) as session:
    probe = session.declare_publisher("magnet/flood-0/raw")
    deadline = time.monotonic() + 10
    while not probe.matching_status.matching and time.monotonic() < deadline:  # the services subscribe magnet/*/raw
        time.sleep(0.02)
    for i in range(8000):
        mag = rng.normal(size=(10, 3)) * 40
        batch = wire.RawBatch(f"flood-{i}", 0, "sim", np.arange(10, dtype=np.int64) + 1, mag, None, None)
        session.put(f"magnet/flood-{i}/raw", wire.encode_raw(batch), congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(1.0)  # the last puts leave the send queue before the session closes
"""


def _rss_mb(pid):
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return 0.0


def _status(service, port):
    code, lines = magnet_json("get", "status", service, *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


def test_forged_and_absurd_calibrations_never_replace_the_signed_one(procs, tmp_path):
    for name in ("calibrator", "forger"):
        assert run_magnet("keys", "--out", str(tmp_path / "keys"), "--name", name).returncode == 0
    cal_port, comp_port, edge_port = free_ports(3)
    trust = ["--trust", str(tmp_path / "keys/calibrator.pub")]
    procs.start(
        "calibrator",
        "calibrator",
        "--db",
        str(tmp_path / "c.db"),
        "--signing-key",
        str(tmp_path / "keys/calibrator.key"),
        *listen_args(cal_port),
    )
    procs.start("compass", "compass", *trust, *listen_args(comp_port), *connect_args(cal_port))
    # the edge dials services that already listen (a peer dialled before it listens may never be reached)
    wait_for(lambda: _status("calibrator", cal_port) and _status("compass", comp_port), 30, "the services to answer")
    procs.start(
        "edge",
        *emulated_edge(DEVICE),
        "--trajectory-samples",
        "2000",
        *listen_args(edge_port),
        *connect_args(cal_port, comp_port),
    )

    def genuine():
        code, lines = magnet_json(
            "get", "calibration", DEVICE, *trust, *NO_SCOUT, *connect_args(cal_port), "--timeout", "2"
        )
        return code == 0 and lines[0]

    record = wait_for(genuine, 60, "a signed calibration")
    wait_for(lambda: (s := _status("compass", comp_port)) and s["calibrations"] == 1, 20, "the compass to apply it")

    forger = subprocess.run(
        [
            sys.executable,
            "-c",
            FORGER,
            str(comp_port),
            __import__("json").dumps(record),
            str(tmp_path / "keys/forger.key"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert forger.returncode == 0, forger.stderr
    forged = int(forger.stdout.split()[-1])
    status = wait_for(
        lambda: (s := _status("compass", comp_port)) and s["dropped_total"] >= forged and s,
        20,
        "the compass to refuse every forged calibration",
    )
    print("compass refusals", status["dropped"])
    assert {
        "calibration:unknown-key",
        "calibration:unsigned",
        "calibration:bad-signature",
        "calibration:bad-calibration",
    } <= set(status["dropped"])
    code, headings = magnet_json(
        "watch", "heading", DEVICE, "--count", "5", *NO_SCOUT, *connect_args(comp_port), timeout=30
    )
    assert code == 0 and len(headings) == 5
    assert all(h["calibration_id"] == record["id"] and h["flags"][0] & 1 for h in headings), (
        "the genuine calibration stays in force"
    )
    code, lines = magnet_json(
        "get",
        "calibration",
        DEVICE,
        "--history",
        "--limit",
        "9" * 26,
        *NO_SCOUT,
        *connect_args(cal_port),
        "--timeout",
        "2",
    )
    assert code == 0 and lines[0]["records"][0]["id"] == record["id"], "the calibrator still answers"
    for name in ("calibrator", "compass", "edge"):
        assert procs.alive(name), procs.log(name)

    # 8,000 new device ids in a burst: both stay up, memory bounded, the genuine device keeps its headings
    before = {name: _rss_mb(procs.procs[name].pid) for name in ("calibrator", "compass")}
    # the calibrator counts every raw message that arrives (new ids beyond its enrolment rate are dropped, counted)
    counted = {"calibrator": "raw_messages", "compass": "received_batches"}
    received = {
        name: _status(name, port)[counted[name]] for name, port in (("calibrator", cal_port), ("compass", comp_port))
    }
    flood = subprocess.run(
        [sys.executable, "-c", FLOOD, str(cal_port), str(comp_port)], capture_output=True, text=True, timeout=120
    )
    assert flood.returncode == 0, flood.stderr
    for name, port in (("calibrator", cal_port), ("compass", comp_port)):
        wait_for(
            lambda name=name, port=port: (s := _status(name, port)) and s[counted[name]] >= received[name] + 8000,
            60,
            f"the {name} to take the flood",
        )
    after = {name: _rss_mb(procs.procs[name].pid) for name in ("calibrator", "compass")}
    print("RSS MB before", before, "after", after)
    for name in before:
        assert after[name] - before[name] < 150, f"{name} grew {after[name] - before[name]:.0f} MB"
    code, headings = magnet_json(
        "watch", "heading", DEVICE, "--count", "5", *NO_SCOUT, *connect_args(comp_port), timeout=30
    )
    assert code == 0 and all(h["calibration_id"] == record["id"] for h in headings)
    for name in ("calibrator", "compass", "edge"):
        assert procs.alive(name), procs.log(name)
