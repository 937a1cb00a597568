"""``magnet bench cost``: what a sample costs, stage by stage, beside the floor a user could write in ten lines.

The log is the simulator's (a car, 100 Hz, ``--minutes`` long, 10 by default: 60,000 samples), written here to
CSV files in a temporary folder. Two tables:

- per stage, microseconds a sample in live batches of 100 samples of one device (decode of the raw wire message,
  calibration, tilt, fusion, aided fusion with fixes at 5 Hz, encode of the heading message, the ROS 2 messages,
  and the compass's whole step), each beside vqf's own cost on the same samples (``updateBatch`` per batch);
- the command line as a user runs it, each a whole process (the least CPU time, user + system, of a few runs; the
  heading with a gyroscope and the fit's figures also as the median of pairs run in turn, against the floor, the
  bare start, and 300 rows against 10,000):
  ``magnet heading`` with a gyroscope and with ``vn,ve,vd`` on every row (a new fix each sample), beside the floor
  (``numpy.loadtxt`` + vqf's ``updateBatch`` on the same file, a process too); ``magnet fit`` of 300 samples beside
  ``python -c 'import numpy, vqf'``; what 10,000 rows add to ``magnet fit`` over 300, and the CSV reader's share.

Targets (issue 28): heading with a gyroscope at most 1.5 x the floor, with velocity on every row at most 3 x; aided
fusion live at most 5 us a sample, ROS 2 at most 3 us; fit of 300 samples at most 1.5 x the bare start; 10,000
rows add at most 15 ms.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

RATE_HZ = 100.0
BATCH = 100
#: live GNSS fixes (Hz) for the aided stage; the command line's log has one on every row
LIVE_FIX_HZ = 5.0
RUNS = 3
#: alternated pairs of whole processes for the fit's figures (their median: a busy machine moves single runs by more
#: than the 15 ms of a target)
PAIRS = 9
FIT_ROWS_SMALL, FIT_ROWS_LARGE = 300, 10_000
TARGETS = {
    "heading_gyro_x": 1.5,
    "heading_velocity_x": 3.0,
    "aided_us": 5.0,
    "ros2_us": 3.0,
    "fit_start_x": 1.5,
    "fit_rows_ms": 15.0,
}
#: the floor: ten lines a user could write instead of ``magnet heading`` (numpy's C reader and vqf's batch)
FLOOR_SCRIPT = """
import sys, numpy, vqf
d = numpy.loadtxt(sys.argv[1], delimiter=",", skiprows=1)
f = vqf.VQF(float(numpy.median(numpy.diff(d[:, 0]))))
out = f.updateBatch(numpy.ascontiguousarray(d[:, 7:10]), numpy.ascontiguousarray(d[:, 4:7]),
                    numpy.ascontiguousarray(d[:, 1:4]))
"""
MAGNET = "import sys; from services.cli import main; sys.exit(main())"


@dataclasses.dataclass(frozen=True)
class Log:
    """A simulated log in the project's body frame: times (N,) s, mag (N, 3) raw uT, acc (N, 3) m/s^2, gyr (N, 3)
    rad/s, the held velocity (N, 3) m/s NED at ``fix_hz`` (NaN before the first fix), and the true calibration."""

    t_s: np.ndarray
    mag_ut: np.ndarray
    acc_ms2: np.ndarray
    gyr_rads: np.ndarray
    vel_ned_ms: np.ndarray
    calibration: object


def simulated_log(minutes: float, fix_hz: float, seed: int = 0) -> Log:
    """A car driving ``minutes`` at 100 Hz with a receiver's velocity at ``fix_hz``."""
    from magnet.simulator import SimulatorConfig, Trajectory, simulate
    from magnet.simulator.gnss import GnssSettings

    count = max(round(minutes * 60 * RATE_HZ), 2 * BATCH)
    config = SimulatorConfig(
        trajectory=Trajectory.CAR, rate_hz=RATE_HZ, count=count, seed=seed, gnss=GnssSettings(rate_hz=fix_hz)
    )
    run = simulate(config)
    assert run.vel_ned_ms is not None  # a moving trajectory has a receiver
    calibration = run.errors.true_calibration(float(run.earth.total_ut))
    return Log(run.t_s, run.mag_ut, run.acc_ms2, run.gyr_rads, run.vel_ned_ms, calibration)


def write_log_csv(path: Path, log: Log, velocity: bool) -> None:
    """The log as ``magnet heading`` reads it: t_s, mx..mz, ax..az, gx..gz (the floor's column order), and
    vn,ve,vd (``nan`` before the first fix) when ``velocity``."""
    header = ["t_s", "mx", "my", "mz", "ax", "ay", "az", "gx", "gy", "gz"]
    columns = [log.t_s[:, None], log.mag_ut, log.acc_ms2, log.gyr_rads]
    if velocity:
        header += ["vn", "ve", "vd"]
        columns.append(log.vel_ned_ms)
    np.savetxt(path, np.hstack(columns), delimiter=",", fmt="%.9g", header=",".join(header), comments="")


def write_fit_csv(path: Path, rows: int) -> None:
    """``rows`` raw samples of a distorted sensor tumbled over the sphere (``magnet bench fit``'s)."""
    from services.bench.fit import synthetic_tumble

    mag, acc = synthetic_tumble(rows)
    np.savetxt(path, np.hstack([mag, acc]), delimiter=",", fmt="%.6f", header="mx,my,mz,ax,ay,az", comments="")


# ------------------------------------------------------------------------------------------------ stages
def _per_sample_us(function: Callable[[], object], samples: int) -> float:
    """CPU microseconds a sample of one call of ``function`` (the process's CPU: a busy machine disturbs it less
    than the wall clock), after one call to warm up when it is cheap."""
    started = time.process_time()
    function()
    return 1e6 * (time.process_time() - started) / samples


def _batches(count: int) -> list[slice]:
    return [slice(lo, min(lo + BATCH, count)) for lo in range(0, count - count % BATCH, BATCH)]


Row = tuple[str, float, float | None]


@dataclasses.dataclass(frozen=True)
class _Live:
    """The log cut into live batches: raw batches without and with velocity, their wire payloads, the calibrated
    field per batch and vqf's inputs per batch (its frame)."""

    parts: list[slice]
    batches: list[Any]
    aided: list[Any]
    payloads: list[bytes]
    field: list[np.ndarray]
    vqf_inputs: list[tuple[np.ndarray, np.ndarray, np.ndarray]]

    @property
    def samples(self) -> int:
        return len(self.parts) * BATCH


def _live(log: Log) -> _Live:
    from magnet import wire
    from magnet.attitude.fusion import to_vqf_frame
    from magnet.model import Calibration

    parts = _batches(len(log.t_s))
    t_ns = (1_700_000_000_000_000_000 + np.round(log.t_s * 1e9)).astype(np.int64)
    batches = [
        wire.RawBatch("bench", i, "sim", t_ns[s], log.mag_ut[s], log.acc_ms2[s], gyr_rads=log.gyr_rads[s])
        for i, s in enumerate(parts)
    ]
    aided = [dataclasses.replace(b, vel_ned_ms=log.vel_ned_ms[s]) for b, s in zip(batches, parts)]
    assert isinstance(log.calibration, Calibration)
    field = [log.calibration.apply(log.mag_ut[s]) for s in parts]
    gyr, acc, mag = (to_vqf_frame(x) for x in (log.gyr_rads, log.acc_ms2, np.vstack(field)))
    inputs = [(gyr[s], acc[s], mag[s]) for s in parts]
    return _Live(parts, batches, aided, [wire.encode_raw(b) for b in batches], field, inputs)


def _filter_rows(log: Log, live: _Live) -> list[Row]:
    """decode, calibration, tilt, fusion (with and without the field's watch) and aided fusion, beside vqf alone."""
    import vqf

    from magnet import wire
    from magnet.attitude import heading as hd
    from magnet.attitude.fusion import Fusion

    period, samples, cal = 1.0 / RATE_HZ, live.samples, log.calibration

    def vqf_alone() -> None:
        f = vqf.VQF(period)
        for g, a, m in live.vqf_inputs:
            f.updateBatch(g, a, m)

    def fusion(aided: bool, watch: bool = True) -> None:
        f = Fusion(period, watch=watch)
        for (g, a, m), s in zip(live.vqf_inputs, live.parts):
            if aided:
                f.update_vqf_frame(g, a, m, log.t_s[s], log.vel_ned_ms[s])
            else:
                f.update_vqf_frame(g, a, m)

    def tilt() -> None:
        for s, f in zip(live.parts, live.field):
            hd.tilt_compensated_heading_deg(f, log.acc_ms2[s])
            hd.disturbance_flags(f, log.acc_ms2[s], 50.0, 60.0)

    vqf_us = _per_sample_us(vqf_alone, samples)
    return [
        ("decode", _per_sample_us(lambda: [wire.decode_raw_many([p]) for p in live.payloads], samples), None),
        ("calibration", _per_sample_us(lambda: [cal.apply(log.mag_ut[s]) for s in live.parts], samples), None),  # type: ignore[attr-defined]
        ("tilt", _per_sample_us(tilt, samples), None),
        ("fusion", _per_sample_us(lambda: fusion(False), samples), vqf_us),
        ("fusion without the field watch", _per_sample_us(lambda: fusion(False, watch=False), samples), vqf_us),
        (f"aided fusion (fixes at {LIVE_FIX_HZ:g} Hz)", _per_sample_us(lambda: fusion(True), samples), vqf_us),
    ]


def _compass_rows(log: Log, live: _Live) -> list[Row]:
    """encode, ROS 2 and the compass's whole step with and without velocity."""
    from magnet import wire
    from magnet.compass import CompassCore
    from services.compass.ros2 import build_drain

    def core() -> CompassCore:
        made = CompassCore()
        made.calibrations.put(wire.DeviceCalibration("bench", 0, log.calibration))  # type: ignore[arg-type]
        return made

    columns = [wire.RawColumns.from_batches([b]) for b in live.batches]
    compass = core()
    outs = [compass.step(c, int(c.t_ns[-1])) for c in columns]

    def step(many: list[Any]) -> None:
        running = core()
        for b in many:
            running.step(wire.RawColumns.from_batches([b]), int(b.t_ns[-1]))

    samples = live.samples
    return [
        ("encode", _per_sample_us(lambda: [compass.encode(c, o) for c, o in zip(columns, outs)], samples), None),
        ("ROS 2", _per_sample_us(lambda: [build_drain(c, o, [0.0]) for c, o in zip(columns, outs)], samples), None),
        ("compass step, gyro", _per_sample_us(lambda: step(live.batches), samples), None),
        ("compass step, aided", _per_sample_us(lambda: step(live.aided), samples), None),
    ]


def stage_costs(log: Log) -> list[Row]:
    """(stage, us a sample, vqf's own us a sample on the same samples or None) in live batches of ``BATCH``."""
    live = _live(log)
    return _filter_rows(log, live) + _compass_rows(log, live)


# ------------------------------------------------------------------------------------------- command line
def _cpu_s(argv: Sequence[str], env: dict[str, str]) -> float:
    """CPU seconds (user + system) of one run of a process, its output thrown away; ValueError when it fails."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(list(argv), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False, env=env)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode not in (0, 1):  # magnet fit exits 1 for a fit its gate refused: still a whole run
        raise ValueError(f"{' '.join(argv[:3])}... failed: {done.stderr.decode(errors='replace')[-300:]}")
    return after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime


def _environment(pycache: Path | None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    if pycache is not None:
        env["PYTHONPYCACHEPREFIX"] = str(pycache)
    return env


def process_s(argv: Sequence[str], runs: int = RUNS, pycache: Path | None = None) -> float:
    """The least CPU seconds (user + system) of ``runs`` runs of a process, its output thrown away: on a shared
    machine the wall clock counts the waits for a core, the CPU time does not. ``pycache``: where the processes
    keep their compiled bytecode (as a user's Python does beside the sources; PYTHONDONTWRITEBYTECODE, which some
    environments set, would make every run compile every module of magnet again). ValueError when it fails."""
    env = _environment(pycache)
    return min(_cpu_s(argv, env) for _ in range(runs))


def process_pairs(
    first: Sequence[str], second: Sequence[str], pairs: int = PAIRS, pycache: Path | None = None
) -> list[tuple[float, float]]:
    """CPU seconds of ``pairs`` runs of two processes in turn (first, second, first, ...): compared pair by pair,
    so a machine whose load drifts moves both alike (``process_s`` for the rest)."""
    env = _environment(pycache)
    return [(_cpu_s(first, env), _cpu_s(second, env)) for _ in range(pairs)]


def _median(values: Sequence[float]) -> float:
    ordered = sorted(values)
    middle = len(ordered) // 2
    return ordered[middle] if len(ordered) % 2 else (ordered[middle - 1] + ordered[middle]) / 2


def command_figures(workdir: Path, minutes: float) -> list[str]:
    """The command-line lines of the report (see the module docstring)."""
    python = sys.executable
    gyro_csv, vel_csv = workdir / "log_gyro.csv", workdir / "log_velocity.csv"
    write_log_csv(gyro_csv, simulated_log(minutes, LIVE_FIX_HZ), velocity=False)
    write_log_csv(vel_csv, simulated_log(minutes, RATE_HZ), velocity=True)  # a new fix on every row
    samples = max(round(minutes * 60 * RATE_HZ), 2 * BATCH)
    lines = []
    process = functools.partial(process_s, pycache=workdir / "pycache")
    process([python, "-c", MAGNET, "heading", str(gyro_csv)], runs=1)  # every module compiled once, kept
    floor_argv = [python, "-c", FLOOR_SCRIPT, str(gyro_csv)]
    gyro_argv = [python, "-c", MAGNET, "heading", str(gyro_csv)]
    floor_vel = process([python, "-c", FLOOR_SCRIPT, str(vel_csv)])
    vel = process([python, "-c", MAGNET, "heading", str(vel_csv)], runs=1)
    turns = process_pairs(gyro_argv, floor_argv, pycache=workdir / "pycache")  # the figure nearest the target's edge
    gyro, floor = min(a for a, _ in turns), min(b for _, b in turns)
    heading_ratios = [a / b for a, b in turns]
    in_turn = f"; {len(turns)} pairs in turn: median {_median(heading_ratios):.2f} x "
    in_turn += f"({min(heading_ratios):.2f}-{max(heading_ratios):.2f})"
    for name, seconds, base, target, paired in (
        ("heading, gyroscope", gyro, floor, TARGETS["heading_gyro_x"], in_turn),
        ("heading, vn,ve,vd on every row", vel, floor_vel, TARGETS["heading_velocity_x"], ""),
    ):
        lines.append(
            f"magnet {name:<31}{seconds:>8.2f} s  {1e6 * seconds / samples:>7.1f} us/sample  "
            f"{seconds / base:>6.2f} x the floor ({base:.2f} s: loadtxt + vqf updateBatch; target <= {target:g} x)"
            f"{paired}"
        )
    small, large = workdir / "fit_small.csv", workdir / "fit_large.csv"
    write_fit_csv(small, FIT_ROWS_SMALL)
    write_fit_csv(large, FIT_ROWS_LARGE)
    fit_small_argv = [python, "-c", MAGNET, "fit", str(small)]
    process(fit_small_argv, runs=1)  # the fit's modules compiled once, kept
    started = process_pairs(fit_small_argv, [python, "-c", "import numpy, vqf"], pycache=workdir / "pycache")
    rows = process_pairs([python, "-c", MAGNET, "fit", str(large)], fit_small_argv, pycache=workdir / "pycache")
    fit_small, bare = min(a for a, _ in started), min(b for _, b in started)
    fit_large = min(a for a, _ in rows)
    ratios = [a / b for a, b in started]
    added_ms = [1e3 * (a - b) for a, b in rows]
    lines.append(
        f"magnet fit of {FIT_ROWS_SMALL} samples           {fit_small:>8.3f} s  {fit_small / bare:>6.2f} x python -c "
        f"'import numpy, vqf' ({bare:.3f} s; target <= {TARGETS['fit_start_x']:g} x); {len(started)} pairs in turn: "
        f"median {_median(ratios):.2f} x ({min(ratios):.2f}-{max(ratios):.2f})"
    )
    lines.append(
        f"magnet fit of {FIT_ROWS_LARGE:,} rows          {fit_large:>8.3f} s  "
        f"adds {_median(added_ms):.0f} ms over {FIT_ROWS_SMALL} (median of {len(rows)} pairs in turn, "
        f"{min(added_ms):.0f} to {max(added_ms):.0f}; target <= {TARGETS['fit_rows_ms']:g} ms); in process (least "
        f"of 5, CPU): the whole command adds {fit_in_process_ms(large) - fit_in_process_ms(small):.1f} ms, the CSV "
        f"reader {reader_ms(large):.1f} ms"
    )
    return lines


def fit_in_process_ms(path: Path, runs: int = 5) -> float:
    """CPU milliseconds (least of ``runs``) of ``magnet fit`` on the CSV at ``path`` run in this process (its modules
    imported already): what the rows cost, without the start of a process, which a busy machine makes vary by more
    than the 15 ms of the target."""
    import contextlib
    import io

    from services.cli import main

    best = float("inf")
    for _ in range(runs):
        started = time.process_time()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            main(["fit", str(path)])
        best = min(best, time.process_time() - started)
    return 1e3 * best


def reader_ms(path: Path, runs: int = 5) -> float:
    """Milliseconds (least of ``runs``) that ``magnet fit``'s reader takes for the CSV at ``path``."""
    from services.common.inputs.csvio import read_samples

    best = float("inf")
    for _ in range(runs):
        started = time.perf_counter()
        read_samples(path)
        best = min(best, time.perf_counter() - started)
    return 1e3 * best


def run_cost_benchmark(minutes: float = 10.0) -> str:
    """Both tables as text (see the module docstring)."""
    log = simulated_log(minutes, LIVE_FIX_HZ)
    lines = [
        (
            f"cost of a sample: a simulated car, {len(log.t_s):,} samples at {RATE_HZ:g} Hz, live batches of "
            f"{BATCH} (CPU us a sample)"
        ),
        f"{'stage':<32}{'us/sample':>10}{'vqf alone':>11}",
    ]
    for name, us, vqf_us in stage_costs(log):
        own = "" if vqf_us is None else f"{vqf_us:>11.2f}"
        lines.append(f"{name:<32}{us:>10.2f}{own}")
    lines.append(
        f"targets: aided fusion <= {TARGETS['aided_us']:g} us/sample, ROS 2 <= {TARGETS['ros2_us']:g} us/sample"
    )
    print("\n".join(lines), flush=True)
    with tempfile.TemporaryDirectory(prefix="magnet-bench-cost-") as workdir:
        commands = command_figures(Path(workdir), minutes)
    return "\n".join(
        [
            "",
            "the command line (whole processes, CPU seconds: least of a few runs; heading and fit also pairs in turn):",
            *commands,
        ]
    )


if __name__ == "__main__":
    print(run_cost_benchmark())
