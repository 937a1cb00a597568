"""The maths must not drag in the network or the bus: importing it loads neither zenoh nor smbus2."""

import subprocess
import sys

MATH_MODULES = ["magnet.model", "magnet.units", "magnet.calibration", "magnet.quality", "magnet.heading",
                "magnet.geomag", "magnet.simulator", "magnet.turntable", "magnet.selftest"]


def test_maths_import_loads_neither_zenoh_nor_smbus2():
    code = (
        "import importlib, sys\n"
        f"for name in {MATH_MODULES!r}:\n"
        "    importlib.import_module(name)\n"
        "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('zenoh', 'smbus2'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"maths imported: {out}"
