"""Two calibrators on one database, each in its own process on loopback: only the one holding the lease collects,
stores and answers for a device; when it is killed (SIGKILL) the other takes over within a bounded time and answers
with what the first one stored. A calibrator of another shard holds its own lease all along."""

from __future__ import annotations

import json
import os
import signal
import time

import pytest
from helpers import NO_SCOUT, connect_args, free_ports, listen_args, magnet_json, wait_for, wait_for_liveliness

from magnet.shard import shard_of

pytestmark = pytest.mark.integration

LOCATION = "50.45,30.52"
TAKEOVER_BOUND_S = 10.0


def _status(name, port):
    code, lines = magnet_json("get", "status", name, *NO_SCOUT, *connect_args(port), "--timeout", "2", timeout=60)
    return lines[0] if code == 0 and lines else None


def _answers(key, ports):
    """Every reply to ``key`` from the calibrators at ``ports`` (no consolidation: two answers stay two)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in ports]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        replies = session.get(key, consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0)
        return [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]


def _calibrator(procs, tmp_path, name, shard, port, *more):
    return procs.start(
        name,
        "calibrator",
        "--name",
        name,
        "--shard",
        shard,
        "--db",
        str(tmp_path / "shared.db"),
        "--location",
        LOCATION,
        *listen_args(port),
        *more,
    )


def test_one_calibrator_writes_and_answers_and_the_other_takes_over_when_it_is_killed(procs, tmp_path):
    port_a, port_b, port_c, edge_port = free_ports(4)
    device = next(f"lease-{i}" for i in range(100) if shard_of(f"lease-{i}", 2) == 0)
    _calibrator(procs, tmp_path, "cal-a", "0/2", port_a)
    wait_for_liveliness(port_a, {"magnet/@alive/calibrator/cal-a"})
    _calibrator(procs, tmp_path, "cal-b", "0/2", port_b, *connect_args(port_a))
    _calibrator(procs, tmp_path, "cal-c", "1/2", port_c, *connect_args(port_a, port_b))
    wait_for(lambda: (s := _status("cal-b", port_b)) and s["lease"] == "standby", 30, "cal-b to stand by")
    wait_for(lambda: (s := _status("cal-c", port_c)) and s["lease"] == "active", 30, "cal-c to hold its shard's lease")
    assert _status("cal-a", port_a)["lease"] == "active"

    procs.start(
        "edge",
        "edge",
        "--device",
        device,
        "--emulate",
        "--rate",
        "500",
        "--batch",
        "25",
        "--hard-iron",
        "25,-15,10",
        "--location",
        LOCATION,
        "--trajectory-samples",
        "2000",
        *listen_args(edge_port),
        *connect_args(port_a, port_b, port_c),
    )
    key = f"magnet/{device}/calibration"
    stored = wait_for(lambda: _answers(key, [port_a, port_b]), 60, "a calibration stored by the active calibrator")
    assert len(stored) == 1, "only the calibrator holding the lease answers"
    a, b = _status("cal-a", port_a), _status("cal-b", port_b)
    assert a["stored"] == 1 and a["received_batches"] > 0
    assert b["stored"] == 0 and b["received_batches"] == 0 and b["devices"]["collecting"] == 0

    os.kill(procs.procs["cal-a"].pid, signal.SIGKILL)
    procs.procs["cal-a"].wait()
    killed = time.monotonic()
    after = wait_for(lambda: _answers(key, [port_b]), TAKEOVER_BOUND_S, "cal-b to take over and answer")
    takeover_s = time.monotonic() - killed
    print(f"takeover answered {takeover_s:.2f} s after SIGKILL")
    assert after == stored, "the calibrator taking over serves what the first one stored"
    b = _status("cal-b", port_b)
    assert b["lease"] == "active" and b["takeovers"] == 1
    assert _status("cal-c", port_c)["takeovers"] == 0
    assert procs.alive("cal-b") and procs.alive("cal-c")
