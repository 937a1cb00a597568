"""``magnet edge`` on a dead (emulated) bus: it does not spin, counts its errors, and says it is unhealthy in its
status reply and in liveliness. A real edge process on loopback; this test's session connects to it."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import msgpack
import pytest
import zenoh

from services.common.zenoh_session import free_ports

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
DEVICE = "dead-1"
UNHEALTHY = f"magnet/@alive/device/{DEVICE}/unhealthy"


def _session(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def _wait(check, timeout_s: float, what: str):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        result = check()
        if result:
            return result
        time.sleep(0.1)
    pytest.fail(f"timed out after {timeout_s} s waiting for {what}")


def _alive(session: zenoh.Session) -> set[str]:
    return {str(r.ok.key_expr) for r in session.liveliness().get("magnet/@alive/**", timeout=1.0) if r.ok is not None}


def _status(session: zenoh.Session) -> dict | None:
    replies = [r.ok for r in session.get(f"magnet/@status/edge-{DEVICE}", timeout=1.0) if r.ok is not None]
    return msgpack.unpackb(replies[0].payload.to_bytes()) if replies else None


def test_edge_on_a_dead_bus_backs_off_counts_errors_and_reports_unhealthy(tmp_path):
    (port,) = free_ports(1)
    duration_s = 5.0
    log = open(tmp_path / "edge.log", "w")
    edge = subprocess.Popen([sys.executable, "-m", "services.cli", "edge", "--device", DEVICE, "--sensor", "hmc5883l",
                             "--emulate", "--emulate-faults", "1", "--rate", "200", "--batch", "10",
                             "--duration", str(duration_s), "--no-multicast-scouting",
                             "--listen", f"tcp/127.0.0.1:{port}"],
                            stdout=subprocess.PIPE, stderr=log, text=True, cwd=ROOT)
    try:
        with _session(port) as session:
            raw = session.declare_subscriber(f"magnet/{DEVICE}/raw", zenoh.handlers.FifoChannel(64))
            _wait(lambda: UNHEALTHY in _alive(session), 15, f"the token {UNHEALTHY}")
            status = _wait(lambda: _status(session), 10, "the edge's status reply")
            assert status["healthy"] is False and status["read_errors"] >= 3, status
            assert "read failed" in status["last_error"] and status["reads"]["errors_by_cause"]["EIO"] >= 3
            assert f"magnet/@alive/device/{DEVICE}" in _alive(session), "the device is alive, only unhealthy"
            out, _ = edge.communicate(timeout=30)
            assert raw.try_recv() is None, "nothing published from a dead bus"
    finally:
        if edge.poll() is None:
            edge.kill()
            edge.wait()
    assert edge.returncode == 0, (tmp_path / "edge.log").read_text()
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["published_samples"] == 0 and summary["healthy"] is False
    assert summary["read_errors"] == summary["read_attempts"] >= 3
    rate = summary["read_attempts"] / summary["seconds"]
    print(f"dead bus: {summary['read_attempts']} read attempts in {summary['seconds']} s ({rate:.1f}/s)")
    assert rate < 10, summary            # bounded by the backoff (was about 1,700 reads/s with read_errors 0)
