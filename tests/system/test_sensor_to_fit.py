"""End to end with no hardware: `magnet sample --emulate` (chip emulator + driver) piped into `magnet fit`."""

from __future__ import annotations

import json
import re
import subprocess

import numpy as np
import pytest
from helpers import MAGNET

HARD_IRON_UT = np.array([25.0, -40.0, 12.0])
SOFT_IRON = np.array([[1.08, 0.03, -0.02], [0.03, 0.95, 0.01], [-0.02, 0.01, 1.02]])
SOFT_IRON_ARG = ",".join(f"{v:g}" for v in SOFT_IRON.ravel())
HARD_IRON_ARG = ",".join(f"{v:g}" for v in HARD_IRON_UT)

pytestmark = pytest.mark.integration


def sample(*options: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            *MAGNET,
            "sample",
            "--emulate",
            "--seed",
            "5",
            "--hard-iron",
            HARD_IRON_ARG,
            "--soft-iron",
            SOFT_IRON_ARG,
            "--noise-ut",
            "0.3",
            *options,
        ],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )


def fit(csv_text: str, *options: str) -> dict:
    result = subprocess.run(
        [*MAGNET, "fit", "/dev/stdin", *options], input=csv_text, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


@pytest.mark.parametrize("sensor", ["lsm303dlh", "qmc5883l"])
def test_emulated_tumble_fitted_with_ellipsoid_recovers_hard_and_soft_iron(sensor: str):
    raw = sample("--sensor", sensor, "--trajectory", "tumble", "--count", "2000").stdout
    record = fit(raw, "--method", "ellipsoid")
    assert np.abs(np.array(record["offset"]) - HARD_IRON_UT).max() < 0.5
    product = np.array(record["matrix"]) @ SOFT_IRON  # identity up to the overall scale
    assert np.allclose(product / np.cbrt(np.linalg.det(product)), np.eye(3), atol=0.01)


def test_emulated_turntable_fitted_with_turntable_recovers_k():
    result = sample("--sensor", "lsm303dlh", "--trajectory", "turntable", "--count", "480")
    horizontal, vertical = re.search(r"--horizontal (\S+) --vertical (\S+)", result.stderr).groups()
    record = fit(result.stdout, "--method", "turntable", "--horizontal", horizontal, "--vertical", vertical)
    k = np.linalg.inv(np.array(record["matrix"]))
    assert np.abs(k - SOFT_IRON).max() < 0.01
    assert np.abs(np.array(record["offset"]) - HARD_IRON_UT).max() < 0.5
