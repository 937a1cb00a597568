"""``magnet edge`` on a dead (emulated) bus: it does not spin, counts its errors, and says it is unhealthy in its
status reply and in liveliness. A real edge process on loopback; this test's session connects to it."""

from __future__ import annotations

import json
import subprocess

import msgpack
import pytest
import zenoh
from helpers import MAGNET, REPO_ROOT, free_ports, listen_args, liveliness_keys, wait_for, wait_for_liveliness

pytestmark = pytest.mark.integration

DEVICE = "dead-1"
UNHEALTHY = f"magnet/@alive/device/{DEVICE}/unhealthy"


def _session(port: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def _status(session: zenoh.Session) -> dict | None:
    replies = [r.ok for r in session.get(f"magnet/@status/edge-{DEVICE}", timeout=1.0) if r.ok is not None]
    return msgpack.unpackb(replies[0].payload.to_bytes()) if replies else None


def test_edge_on_a_dead_bus_backs_off_counts_errors_and_reports_unhealthy(tmp_path):
    (port,) = free_ports(1)
    with open(tmp_path / "edge.log", "w") as log:
        edge = subprocess.Popen(
            [
                *MAGNET,
                "edge",
                "--device",
                DEVICE,
                "--sensor",
                "hmc5883l",
                "--emulate",
                "--emulate-faults",
                "1",
                "--rate",
                "200",
                "--batch",
                "10",
                "--duration",
                "5",
                *listen_args(port),
            ],
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
            cwd=REPO_ROOT,
        )
        try:
            with _session(port) as session:
                raw = session.declare_subscriber(f"magnet/{DEVICE}/raw", zenoh.handlers.FifoChannel(64))
                wait_for_liveliness(port, [UNHEALTHY])
                status = wait_for(lambda: _status(session), 10, "the edge's status reply")
                assert status["healthy"] is False and status["read_errors"] >= 3, status
                assert "read failed" in status["last_error"] and status["reads"]["errors_by_cause"]["EIO"] >= 3
                assert f"magnet/@alive/device/{DEVICE}" in liveliness_keys(port), "alive, only unhealthy"
                out, _ = edge.communicate(timeout=30)
                assert raw.try_recv() is None, "nothing published from a dead bus"
        finally:
            if edge.poll() is None:
                edge.kill()
                edge.communicate()
    assert edge.returncode == 0, (tmp_path / "edge.log").read_text()
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["published_samples"] == 0 and summary["healthy"] is False
    assert summary["read_errors"] == summary["read_attempts"] >= 3
    rate = summary["read_attempts"] / summary["seconds"]
    print(f"dead bus: {summary['read_attempts']} read attempts in {summary['seconds']} s ({rate:.1f}/s)")
    assert rate < 10, summary  # bounded by the backoff (was about 1,700 reads/s with read_errors 0)
