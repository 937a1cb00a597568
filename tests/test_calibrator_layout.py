"""The calibrator's modules stay small enough to read in one sitting, and its public names stay where they were."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 350


def test_every_calibrator_module_is_short():
    long = {
        path.name: n
        for path in sorted((ROOT / "services" / "calibrator").glob("*.py"))
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert long == {}, f"calibrator modules over {MAX_MODULE_LINES} lines: {long}"


def test_the_service_module_still_offers_its_names():
    from services.calibrator import service

    for name in ("Calibrator", "CalibratorSettings", "ServiceSettings", "add_arguments", "run", "run_calibrator"):
        assert hasattr(service, name), name
