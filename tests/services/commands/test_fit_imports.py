"""``magnet fit`` imports what a fit uses: not the services, Zenoh, plotting, ROS 2 or the flight-log readers, and
(for a file without a gyroscope) not the attitude filter (issue 28: its start is most of a small fit's time)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

#: module prefixes a fit of a CSV must not load
NOT_LOADED = (
    "zenoh",
    "matplotlib",
    "plotly",
    "rosbags",
    "mcap",
    "foxglove",
    "pymavlink",
    "pyulog",
    "starlette",
    "uvicorn",
    "cryptography",
    "prometheus_client",
    "magnet.ros2",
    "magnet.attitude.fusion",
    "services.compass",
    "services.edge",
    "services.calibrator",
    "services.dashboard",
    "services.report",
    "services.router",
    "services.common.zenoh_session",
    "services.common.inputs.flightlogs",
    "numpy.ma",  # np.median, np.quantile and np.unique load it (numpy 2.4): magnet.order_stats instead
    "magnet.calibration.field",  # the field ladder: only when the sphere's methods are refused or a rung is asked for
    "magnet.calibration.ladder",
)

SCRIPT = """
import io, json, sys, contextlib
from services.cli import main
with contextlib.redirect_stdout(io.StringIO()):
    status = main(["fit", sys.argv[1]])
print(json.dumps({"status": status, "modules": sorted(sys.modules)}))
"""


@pytest.mark.integration
def test_magnet_fit_of_a_csv_loads_only_what_a_fit_uses(tmp_path):
    rng = np.random.default_rng(0)
    direction = rng.normal(size=(300, 3))
    mag = 50.0 * direction / np.linalg.norm(direction, axis=1, keepdims=True) + [10.0, -20.0, 5.0]
    path = tmp_path / "samples.csv"
    np.savetxt(path, mag, delimiter=",", header="mx,my,mz", comments="", fmt="%.5f")
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["status"] == 0 and "magnet.calibration" in report["modules"]  # the fit ran
    loaded = [m for m in report["modules"] if any(m == p or m.startswith(p + ".") for p in NOT_LOADED)]
    assert loaded == []
