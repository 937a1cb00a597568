"""`magnet up` without a terminal (CI): bounded by --duration, plain lines, every device calibrated, clean exit,
its temporary directory removed."""

import os
import subprocess

import pytest
from helpers import MAGNET, REPO_ROOT

pytestmark = pytest.mark.integration


def test_up_runs_headless_calibrates_every_device_and_stops(tmp_path):
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {**os.environ, "CI": "true", "TMPDIR": str(tmp), "XDG_RUNTIME_DIR": str(tmp_path)}
    out = subprocess.run(
        [
            *MAGNET,
            "up",
            "--devices",
            "3",
            "--speedup",
            "10",
            "--duration",
            "14",
            "--interval",
            "2",
            "--db",
            str(tmp_path / "up.db"),
        ],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=60,
        env=env,
        cwd=REPO_ROOT,
    )
    assert out.returncode == 0, out.stderr
    assert "\x1b[" not in out.stdout, "no terminal codes without a terminal"
    last_view = out.stdout.strip().split("\n\n")[-1].splitlines()
    assert "3 device(s), 3 calibrated" in last_view[0], out.stdout[-2000:]
    rows = [line.split() for line in last_view[2:] if line.startswith("dev-")]
    assert [r[0] for r in rows] == ["dev-000", "dev-001", "dev-002"]
    errors = [abs(float(r[-1])) for r in rows]  # heading error against the simulator's truth, degrees
    assert max(errors) < 5.0, last_view
    assert (tmp_path / "up.db").exists()
    assert "(removed at exit)" in out.stdout and list(tmp.iterdir()) == [], "the temporary directory is removed"
