"""``magnet selftest``: the HMC5883L's built-in self-test (seed 003), on a real bus or the emulator.

Prints whether each axis passed, the bias readings, expected counts and the per-axis scale factors; with
``--emulate --gain-error EX,EY,EZ`` it shows the factors undoing a known sensitivity error, and reads the emulated
field before and after applying them.
"""

from __future__ import annotations

import argparse
import json
import logging
from typing import Any

import numpy as np

from services.common.sim_options import parse_floats

log = logging.getLogger("magnet.drivers.selftest")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sensor", default="hmc5883l", choices=("hmc5883l",), help="only the HMC5883L has it")
    parser.add_argument("--bus", type=int, help="I2C bus number (/dev/i2c-N; 1 on a Raspberry Pi)")
    parser.add_argument("--address", type=lambda s: int(s, 0), default=0x1E, help="I2C address (default 0x1e)")
    parser.add_argument("--emulate", action="store_true", help="test the emulated chip")
    parser.add_argument("--gain", type=int, default=5, help="gain GN for the test (default 5: datasheet limits)")
    parser.add_argument(
        "--gain-error",
        default="0,0,0",
        help="with --emulate: per-axis sensitivity error of the emulated chip, e.g. 0.05,-0.03,0.02",
    )
    parser.add_argument("--temperature-c", type=float, default=25.0, help="with --emulate: chip temperature")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def run(args: argparse.Namespace) -> int:
    from magnet.drivers.hmc5883l import HMC5883L

    gain_error = np.array(parse_floats(args.gain_error, (3,), "--gain-error"))
    if args.emulate:
        from magnet.emulators.base import ConstantSource
        from magnet.emulators.hmc5883l import HMC5883LEmulator

        source = ConstantSource()
        bus: Any = HMC5883LEmulator(
            source, address=args.address, gain_error=gain_error, temperature_c=args.temperature_c, tempco_per_k=-0.003
        )
    else:
        if args.bus is None:
            raise ValueError("a real sensor needs --bus N (1 on a Raspberry Pi), or use --emulate")
        import smbus2

        bus = smbus2.SMBus(args.bus)
    # the emulator answers at once: its data-ready polls need no wait (the same readings, without 0.07 s of sleeps)
    sensor = HMC5883L(bus, args.address, sleep=(lambda _s: None) if args.emulate else None)
    result = sensor.self_test(gain=args.gain)
    if args.json:
        print(json.dumps(result.to_dict()))
        return 0 if result.passed else 1
    print(result.message)
    for i, axis in enumerate("xyz"):
        print(
            f"  {axis}: +bias {result.positive[i]:7.1f}  -bias {result.negative[i]:7.1f}  expected "
            f"{result.expected[i]:6.1f}  limits {result.limits[0]:.0f}..{result.limits[1]:.0f}  "
            f"{'pass' if result.axis_passed[i] else 'FAIL'}  scale {result.scale[i]:.4f}"
        )
    if args.emulate and result.passed:
        raw = _mean_field(sensor)
        sensor.axis_scale = result.scale
        corrected = _mean_field(sensor)
        print(
            f"  emulated true field {np.round(source.mag_ut, 3).tolist()} uT; read {np.round(raw, 3).tolist()} "
            f"uT; with the scale factors {np.round(corrected, 3).tolist()} uT"
        )
    return 0 if result.passed else 1


def _mean_field(sensor, n: int = 8) -> np.ndarray:
    fields = [r.mag_ut for r in (sensor.read() for _ in range(n)) if r.ok]
    return np.mean(fields, axis=0)
