"""Service survival with real processes: ``magnet calibrate DEV rollback`` against a calibrator whose database cannot
grow (sqlite's own "database or disk is full") is refused in words the operator can act on, and the calibrator
keeps answering."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from helpers import NO_SCOUT, REPO_ROOT, connect_args, free_ports, listen_args, magnet_json, run_magnet, wait_for

from magnet import wire
from magnet.model import Calibration
from services.calibrator.store import CalibrationStore

#: the calibrator, with its database unable to grow past the pages it has when opened (a full disk, as sqlite sees
#: it); everything else as ``magnet calibrator`` runs
FULL_DISK_CALIBRATOR = """
import sys
import services.calibrator.store as store
opened = store.CalibrationStore.__init__
def full(self, path):
    opened(self, path)
    pages = self._db.execute("PRAGMA page_count").fetchone()[0]
    self._db.execute(f"PRAGMA max_page_count = {pages}")
store.CalibrationStore.__init__ = full
from services.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _fill(path):
    with CalibrationStore(path) as db:
        for n in (1, 2):  # long reasons: a record needs pages of its own
            cal = Calibration("ellipsoid", [float(n), 0.0, 0.0], np.eye(3), reason="r" * 6000)
            db.save(wire.DeviceCalibration("d1", n, cal))


@pytest.mark.integration
def test_rollback_on_a_full_disk_is_refused_clearly_and_the_calibrator_keeps_answering(tmp_path):
    path = tmp_path / "c.db"
    _fill(path)
    (port,) = free_ports(1)
    log = open(tmp_path / "calibrator.log", "w")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            FULL_DISK_CALIBRATOR,
            "calibrator",
            "--db",
            str(path),
            "--name",
            "cal",
            *listen_args(port),
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=REPO_ROOT,
    )
    remote = [*NO_SCOUT, *connect_args(port), "--timeout", "3"]
    try:
        wait_for(lambda: magnet_json("get", "status", "cal", *remote)[0] == 0, 30, "the calibrator's status")
        out = run_magnet("calibrate", "d1", "rollback", *remote, timeout=30)
        assert out.returncode == 1 and "Traceback" not in out.stderr
        assert "the calibrator could not write its database" in out.stderr and "disk full" in out.stderr, out.stderr
        assert "no calibrator answered" not in out.stderr
        code, (status,) = magnet_json("get", "status", "cal", *remote)
        assert code == 0 and status["dropped"] == {"query:calibrate:handler-StoreError": 1}
        code, (record,) = magnet_json("get", "calibration", "d1", *remote)
        assert code == 0 and record["offset"][0] == 2.0  # nothing changed
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        log.close()
    lines = (tmp_path / "calibrator.log").read_text().splitlines()
    assert "Traceback" not in "\n".join(lines)
    assert sum("handler failed" in line for line in lines) == 1
