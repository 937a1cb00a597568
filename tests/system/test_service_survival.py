"""Service survival with real processes: ``magnet calibrate DEV rollback`` against a calibrator whose database cannot
grow (sqlite's own "database or disk is full") is refused in words the operator can act on, and the calibrator
keeps answering; a flood of new device ids is bounded and counted while the status answers within a second."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from helpers import (
    NO_SCOUT,
    REPO_ROOT,
    Processes,
    connect_args,
    free_ports,
    listen_args,
    magnet_json,
    run_magnet,
    wait_for,
)

from magnet import wire
from magnet.model import Calibration
from services.bench.flood import rss_mb
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
        assert code == 0 and status["dropped"] == {}  # refused by the rollback itself, not a handler failure
        code, (record,) = magnet_json("get", "calibration", "d1", *remote)
        assert code == 0 and record["offset"][0] == 2.0  # nothing changed
        assert proc.poll() is None
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        log.close()
    lines = (tmp_path / "calibrator.log").read_text().splitlines()
    assert "Traceback" not in "\n".join(lines)
    assert sum("rollback of d1 refused" in line and "disk full" in line for line in lines) == 1  # one line


def _json_line(proc: subprocess.Popen[str]) -> dict:
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.integration
def test_a_flood_of_new_ids_is_bounded_counted_and_status_answers_within_a_second(tmp_path):
    """80,000 messages of new device ids at up to 10,000/s from one process while another asks the calibrator's
    status, @fleet and a calibration in turn every 0.2 s: every answer in under 1 s, every message counted
    (processed or dropped by cause), memory bounded by --max-devices."""
    (port,) = free_ports(1)
    _fill(tmp_path / "c.db")  # d1 has a calibration to ask for
    procs = Processes(tmp_path)
    flood = [sys.executable, "-m", "services.bench.flood"]
    try:
        calibrator = procs.start(
            "calibrator", "calibrator", "--db", str(tmp_path / "c.db"), "--name", "cal", "--max-devices", "2000",
            *listen_args(port),
        )  # fmt: skip
        remote = [*NO_SCOUT, *connect_args(port), "--timeout", "3"]
        wait_for(lambda: magnet_json("get", "status", "cal", *remote)[0] == 0, 30, "the calibrator's status")
        rss_before = rss_mb(calibrator.pid)
        prober = subprocess.Popen(
            [*flood, "probe", "--port", str(port), "--name", "cal", "--key", "magnet/@fleet",
             "--key", "magnet/d1/calibration", "--period", "0.2", "--seconds", "14"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO_ROOT,
        )  # fmt: skip
        sender = subprocess.Popen(
            [*flood, "ids", "--port", str(port), "--count", "80000", "--rate", "10000"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO_ROOT,
        )  # fmt: skip
        sent = _json_line(sender)
        probed = _json_line(prober)
        status = wait_for(
            lambda: (s := magnet_json("get", "status", "cal", *remote)[1]) and s[0]["queued"] == 0 and s[0],
            30,
            "the queue to empty",
        )
        rss_after = rss_mb(calibrator.pid)
        assert calibrator.poll() is None
    finally:
        procs.stop_all()
    raw_drops = {cause: n for cause, n in status["dropped"].items() if cause.startswith("raw:")}
    print(f"flood {sent}; answers {probed['answered']}/{probed['asked']}, worst {probed['worst_s']} s;")
    print(f"counted {status['raw_messages']} = {status['received_batches']} processed + {raw_drops};")
    print(f"enrolled {status['enrolled']}, queue high water {status['queue_high_water']};", end=" ")
    print(f"RSS {rss_before:.0f} -> {rss_after:.0f} MB")
    assert probed["asked"] >= 40 and probed["answered"] == probed["asked"], probed
    assert all(worst < 1.0 for worst in probed["worst_s"].values()), probed  # status, @fleet, a calibration
    assert status["raw_messages"] == sent["sent"] == 80_000
    assert status["raw_messages"] == status["received_batches"] + sum(raw_drops.values())
    assert raw_drops.get("raw:enrol-rate", 0) > 0  # the flood was limited, and said so
    assert status["enrolled"] <= 2000 + 200 * (sent["seconds"] + 30)  # the burst, then the rate
    assert status["devices"]["collecting"] <= 2000  # --max-devices
    assert rss_after - rss_before < 200  # 80,000 ids: 2,000 devices and the queue (at most --max-queue messages)


@pytest.mark.integration
def test_rollback_with_the_database_on_a_full_filesystem_is_refused_and_the_calibrator_keeps_answering(tmp_path):
    """The same on a real full filesystem: a small tmpfs under the database, filled to its last block (needs root
    and tmpfs, else skipped)."""
    from services.bench.soak import FullDisk

    disk = FullDisk(tmp_path / "db")
    if not disk.mounted:
        pytest.skip(f"no tmpfs: {disk.why_not}")
    (port,) = free_ports(1)
    procs = Processes(tmp_path)
    remote = [*NO_SCOUT, *connect_args(port), "--timeout", "3"]
    try:
        db = disk.directory / "c.db"
        _fill(db)
        procs.start("calibrator", "calibrator", "--db", str(db), "--name", "cal", *listen_args(port))
        wait_for(lambda: magnet_json("get", "status", "cal", *remote)[0] == 0, 30, "the calibrator's status")
        disk.fill()
        out = run_magnet("calibrate", "d1", "rollback", *remote, timeout=30)
        assert out.returncode == 1 and "Traceback" not in out.stderr
        assert "could not write its database" in out.stderr and "disk full" in out.stderr, out.stderr
        code, (status,) = magnet_json("get", "status", "cal", *remote)
        assert code == 0 and status["dropped"] == {}  # refused by the rollback itself, not a handler failure
        disk.free()
        out = run_magnet("calibrate", "d1", "rollback", *remote, timeout=30)
        assert out.returncode == 0, out.stderr  # space again: the same request goes through
        assert procs.alive("calibrator")
    finally:
        procs.stop_all()
        disk.unmount()
