"""`magnet router` carries traffic between clients: a calibrator and a remote tool that only know the router."""

import json
import signal
import subprocess

import pytest
from helpers import MAGNET, free_ports, run_magnet, wait_for

pytestmark = pytest.mark.integration


def test_clients_meet_through_the_router(tmp_path):
    (port,) = free_ports(1)
    client = ["--mode", "client", "--no-multicast-scouting", "--connect", f"tcp/127.0.0.1:{port}"]
    router = subprocess.Popen([*MAGNET, "router", "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"])
    calibrator = subprocess.Popen([*MAGNET, "calibrator", "--db", str(tmp_path / "c.db"), *client])
    try:
        out = wait_for(
            lambda: (
                (answer := run_magnet("get", "status", "calibrator", *client, "--timeout", "1", timeout=20)).returncode
                == 0
                and answer
            ),
            20,
            "the calibrator's status through the router",
        )
        assert json.loads(out.stdout)["service"] == "calibrator"
        missing = run_magnet("get", "calibration", "nobody", *client, "--timeout", "1", timeout=20)
        assert missing.returncode == 1 and "no calibration for nobody" in missing.stderr
    finally:
        for proc in (calibrator, router):
            proc.send_signal(signal.SIGTERM)
        assert calibrator.wait(timeout=10) == 0 and router.wait(timeout=10) == 0
