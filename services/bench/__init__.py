"""``magnet bench accuracy|fit|pipeline|motion|field|fleet|dashboard|soak|cost|store``: benchmarks that print figures
(targets live here, not in timed tests)."""

from __future__ import annotations

import argparse
import importlib

#: benchmark -> (module, function)
BENCHMARKS: dict[str, tuple[str, str]] = {
    "accuracy": ("services.bench.accuracy", "run_accuracy_benchmark"),
    "fit": ("services.bench.fit", "run_fit_benchmark"),
    "pipeline": ("services.bench.pipeline", "run_pipeline_benchmark"),
    "motion": ("services.bench.motion_table", "run_motion_benchmark"),
    "field": ("services.bench.field", "run_field_benchmark"),
    "fleet": ("services.bench.fleet_query", "run_fleet_benchmark"),
    "dashboard": ("services.bench.dashboard", "run_dashboard_benchmark"),
    "soak": ("services.bench.soak", "run_soak_benchmark"),
    "cost": ("services.bench.cost", "run_cost_benchmark"),
    "store": ("services.bench.store", "run_store_benchmark"),
}


def parse_seeds(text: str) -> tuple[int, ...]:
    """``--seeds``: comma-separated whole numbers >= 0, at least one."""
    try:
        seeds = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seeds must be comma-separated whole numbers, got {text!r}") from None
    if not seeds or min(seeds) < 0:
        raise argparse.ArgumentTypeError(f"--seeds needs at least one whole number >= 0, got {text!r}")
    return seeds


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("benchmark", choices=sorted(BENCHMARKS))
    parser.add_argument("--devices", type=int, default=1000, help="pipeline: simulated devices (default 1000)")
    parser.add_argument("--rate", type=float, default=100.0, help="pipeline: samples/s per device (default 100)")
    parser.add_argument("--batch", type=int, default=10, help="pipeline: samples per message (default 10)")
    parser.add_argument("--seconds", type=float, default=10.0, help="pipeline: measuring time per rate (default 10)")
    parser.add_argument(
        "--shards",
        type=int,
        default=2,
        help="pipeline: compass shards compared against 1 at the end (default 2; 1: no comparison)",
    )
    parser.add_argument(
        "--minutes",
        type=float,
        default=10.0,
        help="soak: minutes under the schedule of faults; cost: minutes of the simulated log (default 10)",
    )
    parser.add_argument(
        "--no-gyro", action="store_true", help="pipeline: devices without gyroscopes (accelerometer tilt, no fusion)"
    )
    parser.add_argument(
        "--broad-dir",
        default=None,
        help="motion: score every BROAD trial (broad_*.npz) of this directory against vqf (docs/broad-motion.md)",
    )
    parser.add_argument(
        "--seeds",
        type=parse_seeds,
        default=None,
        metavar="N,N,...",
        help="field: the simulator's seeds (default 2026,2027,2028: not the ones tuned on, 1-9)",
    )
    parser.add_argument(
        "--db",
        default=None,
        metavar="FILE.sqlite3|postgresql://...",
        help="store: the store measured (an empty PostgreSQL database, or a new SQLite file; default a temporary file)",
    )
    parser.add_argument("--json", action="store_true", help="field: every run's figures as JSON instead of the table")
    parser.add_argument(
        "--samples", default=None, metavar="FILE.json", help="soak: write every RSS sample to this file (JSON)"
    )
    parser.add_argument(
        "--ros2", action="store_true", help="pipeline: the compass's cost of also publishing ROS 2 messages, at --rate"
    )


def run(args: argparse.Namespace) -> int:
    module_name, function_name = BENCHMARKS[args.benchmark]
    function = getattr(importlib.import_module(module_name), function_name)
    if args.benchmark == "pipeline":
        if args.devices < 1 or args.rate <= 0 or args.batch < 1 or args.seconds <= 0 or args.shards < 1:
            raise ValueError("--devices, --rate, --batch, --seconds and --shards must be positive")
        result = function(
            devices=args.devices,
            rate=args.rate,
            batch=args.batch,
            seconds=args.seconds,
            shards=args.shards,
            gyro=not args.no_gyro,
            ros2=args.ros2,
        )
    elif args.benchmark == "dashboard":
        if args.devices < 1 or args.seconds <= 0:
            raise ValueError("--devices and --seconds must be positive")
        result = function(devices=args.devices, seconds=args.seconds)
    elif args.benchmark in ("soak", "cost"):
        if not args.minutes > 0:
            raise ValueError("--minutes must be positive")
        extra = {"samples": args.samples} if args.benchmark == "soak" and args.samples else {}
        result = function(minutes=args.minutes, **extra)
    elif args.benchmark == "motion" and getattr(args, "broad_dir", None):
        result = importlib.import_module("services.bench.motion_broad").run_broad_dir(args.broad_dir)
    elif args.benchmark == "field":
        result = function(**({"seeds": args.seeds} if args.seeds is not None else {}), as_json=args.json)
    elif args.benchmark == "store":
        from services.common.stores import parse_db

        if args.devices < 1:
            raise ValueError("--devices must be positive")
        result = function(devices=args.devices, db=None if args.db is None else parse_db(args.db))
    elif args.benchmark == "fleet":
        if args.devices < 1:
            raise ValueError("--devices must be positive")
        result = function(devices=args.devices)
    else:
        result = function()
    if isinstance(result, str):
        print(result)
    return 0
