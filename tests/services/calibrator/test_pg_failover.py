"""Calibrators on two hosts (separate working directories, no shared file) on one PostgreSQL database: five devices
in force (one calibrated live by the active calibrator), which is killed with SIGKILL; the standby takes over and
serves every record, exactly as stored. And a commit cut by kill -9 in the middle of its transaction is absent, never
half there, and the next writer carries on."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from helpers import NO_SCOUT, REPO_ROOT, connect_args, free_ports, listen_args, magnet_json, wait_for
from memory_store import record_of

from magnet import wire
from services.calibrator.store import open_store
from services.common.stores import parse_db

pytestmark = pytest.mark.integration

LOCATION = "50.45,30.52"
DEVICES = [f"pg-{i:03d}" for i in range(5)]


def _status(name, port):
    code, lines = magnet_json("get", "status", name, *NO_SCOUT, *connect_args(port), "--timeout", "2", timeout=60)
    return lines[0] if code == 0 and lines else None


def _records(port):
    """device -> the calibration record served through 127.0.0.1:port (every replier, no consolidation)."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as session:
        replies = session.get("magnet/*/calibration", consolidation=zenoh.ConsolidationMode.NONE, timeout=2.0)
        payloads = [reply.ok.payload.to_bytes() for reply in replies if reply.ok is not None]
    return {wire.decode_calibration(p).device: p for p in payloads}


def test_the_standby_on_another_host_serves_every_record_after_the_active_one_is_killed(procs, tmp_path, postgres_url):
    with open_store(parse_db(postgres_url)) as store:  # four records stored earlier, the fifth calibrated live
        for n, device in enumerate(DEVICES[1:]):
            store.append(device, lambda v, d=device, n=n: record_of(d, v, float(n), created_ns=time.time_ns()))
    host_a, host_b = tmp_path / "host-a", tmp_path / "host-b"
    host_a.mkdir(), host_b.mkdir()
    port_a, port_b, edge_port = free_ports(3)
    common = ("--db", postgres_url, "--location", LOCATION)
    procs.start("cal-a", "calibrator", "--name", "cal-a", *common, *listen_args(port_a), cwd=host_a)
    wait_for(lambda: (s := _status("cal-a", port_a)) and s["lease"] == "active", 30, "cal-a to hold the lease")
    procs.start(
        "cal-b", "calibrator", "--name", "cal-b", *common, *listen_args(port_b), *connect_args(port_a), cwd=host_b
    )
    wait_for(lambda: (s := _status("cal-b", port_b)) and s["lease"] == "standby", 30, "cal-b to stand by")
    procs.start(
        "edge",
        "edge",
        *("--device", DEVICES[0], "--emulate", "--rate", "500", "--batch", "25"),
        *("--hard-iron", "25,-15,10", "--location", LOCATION, "--trajectory-samples", "2000"),
        *listen_args(edge_port),
        *connect_args(port_a, port_b),
    )
    served = wait_for(lambda: len(r := _records(port_a)) == 5 and r, 60, "the fifth calibration stored by cal-a")
    assert sorted(served) == DEVICES

    os.kill(procs.procs["cal-a"].pid, signal.SIGKILL)
    procs.procs["cal-a"].wait()
    killed = time.monotonic()
    after = wait_for(lambda: len(r := _records(port_b)) == 5 and r, 20, "cal-b to take over and serve all five")
    print(f"standby served 5/5 records {time.monotonic() - killed:.2f} s after SIGKILL")
    assert after == served, "the standby serves every record exactly as the killed calibrator stored it"
    assert _status("cal-b", port_b)["takeovers"] == 1
    assert not list(host_b.glob("**/*.db")) and not list(host_a.glob("**/*.db")), "no SQLite file on either host"
    with open_store(parse_db(postgres_url)) as store:
        assert {d: [r.version for r in store.history(d)] for d in DEVICES} == {d: [1] for d in DEVICES}


KILLED_MID_COMMIT = """
import os, sys, time
sys.path.insert(0, {tests!r})
from memory_store import record_of

from magnet import wire
from services.common.stores import parse_db
from services.calibrator.store import open_store
from services.calibrator import pgstore

insert = pgstore.PostgresStore._insert
def insert_then_hang(conn, row):
    insert(conn, row)  # the record row and its change are written, the transaction not committed
    print("inserted", flush=True)
    time.sleep(60)
pgstore.PostgresStore._insert = staticmethod(insert_then_hang)
store = open_store(parse_db({url!r}))
store.append("cut", lambda v: record_of("cut", v, 9.0), {{"action": "auto"}})
"""


def test_a_commit_cut_by_kill_9_is_absent_and_the_next_writer_carries_on(postgres_url):
    with open_store(parse_db(postgres_url)) as store:
        first, _ = store.append("cut", lambda v: record_of("cut", v, 1.0), {"action": "auto"})
        code = textwrap.dedent(KILLED_MID_COMMIT.format(tests=str(REPO_ROOT / "tests"), url=postgres_url))
        with subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, cwd=REPO_ROOT) as child:
            try:
                assert child.stdout is not None and child.stdout.readline().strip() == "inserted"
            finally:
                os.kill(child.pid, signal.SIGKILL)
        # the server rolls the cut transaction back and frees its device lock: the next append is version 2
        second, stored = wait_for(
            lambda: store.append("cut", lambda v: record_of("cut", v, 2.0), {"action": "auto"}), 10, "the lock freed"
        )
        assert stored and second.version == 2
        assert [(r.id, c) for r, c in store.history_changes("cut")] == [
            (second.id, {"action": "auto"}),
            (first.id, {"action": "auto"}),
        ], "nothing of the cut commit is stored"
