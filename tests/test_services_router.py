"""`magnet router` carries traffic between clients: a calibrator and a remote tool that only know the router."""

import json
import signal
import subprocess
import sys
import time

from services.common.zenoh_session import free_ports

MAGNET = [sys.executable, "-m", "services.cli"]


def test_clients_meet_through_the_router(tmp_path):
    (port,) = free_ports(1)
    client = ["--mode", "client", "--no-multicast-scouting", "--connect", f"tcp/127.0.0.1:{port}"]
    router = subprocess.Popen([*MAGNET, "router", "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"])
    calibrator = subprocess.Popen([*MAGNET, "calibrator", "--db", str(tmp_path / "c.db"), *client])
    try:
        deadline = time.monotonic() + 20
        while True:
            out = subprocess.run([*MAGNET, "get", "status", "calibrator", *client, "--timeout", "1"],
                                 capture_output=True, text=True, timeout=20)
            if out.returncode == 0 or time.monotonic() > deadline:
                break
            time.sleep(0.3)
        assert out.returncode == 0, out.stderr
        assert json.loads(out.stdout)["service"] == "calibrator"
        missing = subprocess.run([*MAGNET, "get", "calibration", "nobody", *client, "--timeout", "1"],
                                 capture_output=True, text=True, timeout=20)
        assert missing.returncode == 1 and "no calibration for nobody" in missing.stderr
    finally:
        for proc in (calibrator, router):
            proc.send_signal(signal.SIGTERM)
        assert calibrator.wait(timeout=10) == 0 and router.wait(timeout=10) == 0
