"""msgpack bombs at the raw key of a running compass and calibrator (real processes on loopback): 20 payloads of
4 MB each holding a 4-million-element array (refused by size). Both services refuse and count every one, their
memory grows by at most 50 MB, and the headings of a genuine device keep flowing (longest gap under 0.5 s). The
bomber can also send 2.5 MB of empty arrays, within the raw size limit (``kind`` "empty-containers")."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from helpers import NO_SCOUT, connect_args, emulated_edge, listen_args, magnet_json, wait_for

pytestmark = pytest.mark.integration

DEVICE = "bomb-ok"
BOMBS = 20

#: a plain Zenoh peer (argv: the services' ports) that watches DEVICE's headings, then sends the bombs at other
#: devices' raw keys and prints the arrival gaps of the headings around them (JSON)
BOMBER = r"""
import json, sys, threading, time, zenoh
device, bombs, kind, ports = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4:]
if kind == "array":
    four_mb = 4 * 1024 * 1024
    bomb = b"\xdd" + (four_mb - 5).to_bytes(4, "big") + b"\x00" * (four_mb - 5)
else:  # a map of 250 arrays of 10,000 empty arrays
    inner = b"\xdd" + (10_000).to_bytes(4, "big") + b"\x90" * 10_000
    bomb = b"\x81\xa3big\xdd" + (250).to_bytes(4, "big") + inner * 250
arrivals, lock = [], threading.Lock()
def on_heading(sample):
    with lock:
        arrivals.append(time.monotonic())
conf = zenoh.Config()
conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in ports]))
conf.insert_json5("scouting/multicast/enabled", "false")
with zenoh.open(conf) as session:
    sub = session.declare_subscriber(f"magnet/{device}/heading", on_heading)
    probe = session.declare_publisher("magnet/bomb-0/raw")
    deadline = time.monotonic() + 20
    while (not probe.matching_status.matching or len(arrivals) < 20) and time.monotonic() < deadline:
        time.sleep(0.05)
    start = time.monotonic()
    for i in range(bombs):
        session.put(f"magnet/bomb-{i}/raw", bomb, congestion_control=zenoh.CongestionControl.BLOCK)
    sent = time.monotonic()
    time.sleep(3.0)
    with lock:
        window = [start - 0.5] + [t for t in arrivals if t >= start - 0.5] + [time.monotonic()]
    gaps = [b - a for a, b in zip(window, window[1:])]
    print(json.dumps({"size": len(bomb), "send_s": sent - start, "headings": len(window) - 2,
                      "longest_gap_s": max(gaps) if gaps else None}))
"""


def _memory_mb(pid):
    """(VmRSS, VmHWM) of a process, MB."""
    out = {}
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = int(line.split()[1]) / 1024
    return out["VmRSS"], out["VmHWM"]


def _status(service, port):
    code, lines = magnet_json("get", "status", service, *NO_SCOUT, *connect_args(port), "--timeout", "2")
    return lines[0] if code == 0 and lines else None


#: "empty-containers": 2.5 MB of empty arrays, within the raw size limit, stopped by the count of containers; the
#: compass's growth is bounded by its byte-bounded intake (measured +25 MB, most of it Zenoh's receiving buffers)
def _compass_has_its_intake():
    """Whether the compass takes raw samples through its byte-bounded intake (services/compass/intake.py)."""
    from pathlib import Path

    import services.compass.service as service

    return "PayloadIntake" in Path(service.__file__).read_text()


@pytest.mark.parametrize(
    "kind",
    [
        "array",
        pytest.param(
            "empty-containers",
            marks=pytest.mark.skipif(
                not _compass_has_its_intake(),
                reason="without its byte-bounded intake the compass copies a whole burst of 2.5 MB bombs (+58 MB)",
            ),
        ),
    ],
)
def test_msgpack_bombs_are_refused_without_memory_and_headings_keep_flowing(procs, tmp_path, kind):
    cal_port, comp_port, edge_port = procs.start_services()
    wait_for(lambda: _status("calibrator", cal_port) and _status("compass", comp_port), 30, "the services to answer")
    procs.start(
        "edge",
        *emulated_edge(DEVICE),
        *listen_args(edge_port),
        *connect_args(cal_port, comp_port),
    )
    wait_for(lambda: (s := _status("compass", comp_port)) and s["received_batches"] > 20, 30, "headings to flow")
    ports = {"calibrator": cal_port, "compass": comp_port}
    before = {name: _memory_mb(procs.procs[name].pid) for name in ports}
    dropped = {name: _status(name, port)["dropped_total"] for name, port in ports.items()}

    bomber = subprocess.run(
        [sys.executable, "-c", BOMBER, DEVICE, str(BOMBS), kind, str(cal_port), str(comp_port)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bomber.returncode == 0, bomber.stderr
    result = json.loads(bomber.stdout.strip().splitlines()[-1])
    for name, port in ports.items():
        status = wait_for(
            lambda name=name, port=port: (
                (s := _status(name, port)) and s["dropped_total"] >= dropped[name] + BOMBS and s
            ),
            30,
            f"the {name} to refuse every bomb",
        )
        refused = status["dropped"].get("raw:oversized", 0) + status["dropped"].get("raw:queue-full", 0)
        assert refused >= BOMBS, status["dropped"]  # a burst beyond the compass's queue is dropped before decoding
    after = {name: _memory_mb(procs.procs[name].pid) for name in ports}
    print("bombs", kind, result)
    for name in ports:
        print(
            f"{name}: RSS {before[name][0]:.0f} -> {after[name][0]:.0f} MB, peak {before[name][1]:.0f} -> "
            f"{after[name][1]:.0f} MB"
        )
    for name in ports:
        assert after[name][0] - before[name][0] <= 50, f"{name} grew {after[name][0] - before[name][0]:.0f} MB"
        assert procs.alive(name), procs.log(name)
    assert result["headings"] > 20 and result["longest_gap_s"] < 0.5, result
