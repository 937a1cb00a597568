"""``magnet up``: the whole pipeline on this machine, with a live view.

N emulated devices (one ``magnet edge --emulate --devices N`` process: each device its own hard and soft iron), a
calibrator (SQLite in ``--db`` or a temporary directory) and a compass, each in its own process (started with
subprocess, before this process opens its own session), on 127.0.0.1 with explicit ports and multicast scouting off.
The view shows per device: calibration state and sphere coverage while collecting, then the true heading, pitch,
roll, the calibration residual, and the heading error against the simulator's truth. On a terminal it redraws in
place; without one (CI, pipes) it prints plain lines every few seconds. Ctrl-C (or ``--duration``) stops everything.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import zenoh

from magnet import wire
from magnet.geomag import parse_location
from services.common.sim_options import SimulatorSettings
from services.common.zenoh_session import free_ports, loopback_arguments, payload_bytes, stop_event
from services.edge.settings import EdgeSettings

log = logging.getLogger("magnet.up")

SERVICES = ("calibrator", "compass", "edge")
MAX_DEVICES = 10_000
LOG_TAIL_LINES = 15


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--devices", type=int, default=4, help="emulated devices (default 4)")
    parser.add_argument("--rate", type=float, default=50.0, help="samples per second per device (default 50)")
    parser.add_argument("--batch", type=int, default=10, help="samples per message (default 10)")
    parser.add_argument(
        "--speedup",
        type=float,
        default=4.0,
        help="the emulated devices tumble this many times faster than real time (default 4)",
    )
    parser.add_argument("--location", default="50.45,30.52", help="LAT,LON[,ALT_M] of the devices (default Kyiv)")
    parser.add_argument("--db", type=Path, help="calibration database (default: a temporary directory)")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    parser.add_argument("--interval", type=float, help="seconds between views (default 0.5 on a terminal, else 3)")
    parser.add_argument("--prefix", default=wire.DEFAULT_PREFIX, help="key prefix")
    parser.add_argument(
        "--http",
        metavar="HOST:PORT",
        help="where the dashboard serves its page (default 127.0.0.1:8080, or a free port when taken)",
    )
    parser.add_argument("--no-dashboard", action="store_true", help="do not start the web dashboard")


@dataclasses.dataclass(frozen=True)
class UpSettings:
    """What ``magnet up`` runs, checked in one place before anything starts: the edge's own checks (rate, batch,
    speedup) through the ``EdgeSettings`` it will run, the location through ``parse_location``."""

    devices: int = 4
    rate_hz: float = 50.0
    batch: int = 10
    speedup: float = 4.0
    location: str = "50.45,30.52"
    db: Path | None = None
    duration_s: float | None = None
    interval_s: float | None = None
    prefix: str = wire.DEFAULT_PREFIX
    http: str | None = None
    dashboard: bool = True

    def __post_init__(self) -> None:
        if self.http is not None:
            from services.dashboard.service import parse_http

            parse_http(self.http)
        if not 1 <= self.devices <= MAX_DEVICES:
            raise ValueError(f"--devices must be 1..{MAX_DEVICES}, got {self.devices}")
        if self.duration_s is not None and not self.duration_s >= 0:
            raise ValueError(f"--duration must be >= 0 seconds, got {self.duration_s}")
        if self.interval_s is not None and not self.interval_s > 0:
            raise ValueError(f"--interval must be > 0 seconds, got {self.interval_s}")
        wire.validate_prefix(self.prefix)
        try:
            place = parse_location(self.location)
        except ValueError as exc:
            raise ValueError(f"--location: {exc}") from None
        EdgeSettings(
            device="dev",
            emulate=True,
            devices=self.devices,
            rate_hz=self.rate_hz,
            batch=self.batch,
            speedup=self.speedup,
            simulator=SimulatorSettings(location=place),
        )

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> UpSettings:
        return cls(
            devices=int(args.devices),
            rate_hz=float(args.rate),
            batch=int(args.batch),
            speedup=float(args.speedup),
            location=args.location,
            db=args.db,
            duration_s=args.duration,
            interval_s=args.interval,
            prefix=args.prefix,
            http=args.http,
            dashboard=not args.no_dashboard,
        )


@dataclasses.dataclass
class DeviceView:
    """What the view knows of one device."""

    state: str = "waiting"
    coverage: float | None = None
    samples: int | None = None
    missing: tuple[str, ...] = ()
    reason: str = ""
    residual_ut: float | None = None
    calibration_id: str = ""
    true_heading_deg: float | None = None
    pitch_deg: float | None = None
    roll_deg: float | None = None
    flags: int = 0
    truth: dict[int, float] = dataclasses.field(default_factory=dict)  # seq -> true heading of the last sample
    error_deg: float | None = None

    def on_progress(self, message: dict[str, Any]) -> None:
        self.state = str(message.get("state", self.state))
        self.coverage = message.get("coverage", self.coverage)
        self.samples = message.get("samples", self.samples)
        self.missing = tuple(message.get("missing") or ())
        self.reason = str(message.get("reason") or "")
        self.residual_ut = message.get("residual_rms_ut", self.residual_ut)
        self.calibration_id = message.get("calibration_id") or self.calibration_id

    def on_calibration(self, message: dict[str, Any]) -> None:
        self.state = "calibrated"
        self.calibration_id = str(message.get("id", ""))
        self.residual_ut = (message.get("quality") or {}).get("residual_rms_ut", self.residual_ut)
        self.coverage = (message.get("quality") or {}).get("coverage", self.coverage)

    def on_raw(self, batch: wire.RawBatch) -> None:
        if batch.truth is not None:
            self.truth[batch.seq] = float(batch.truth["heading_deg"][-1])
            if len(self.truth) > 64:
                self.truth.pop(next(iter(self.truth)))

    def on_heading(self, batch: wire.HeadingBatch) -> None:
        self.true_heading_deg = float(batch.true_heading_deg[-1])
        self.pitch_deg, self.roll_deg = float(batch.pitch_deg[-1]), float(batch.roll_deg[-1])
        self.flags = int(batch.flags[-1])
        truth = self.truth.get(batch.seq)
        if truth is not None:
            self.error_deg = float((self.true_heading_deg - truth + 180.0) % 360.0 - 180.0)


def _bar(fraction: float | None, width: int = 20) -> str:
    if fraction is None:
        return "[" + "?" * width + "]"
    filled = round(max(0.0, min(1.0, fraction)) * width)
    return "[" + "#" * filled + "." * (width - filled) + f"] {fraction:4.0%}"


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None or not np.isfinite(value) else format(value, spec)


def render_lines(views: dict[str, DeviceView], elapsed_s: float) -> list[str]:
    """The view as lines of text (no terminal codes)."""
    calibrated = sum(v.state == "calibrated" for v in views.values())
    lines = [
        f"magnet up: {len(views)} device(s), {calibrated} calibrated, {elapsed_s:5.1f} s   (Ctrl-C stops)",
        (
            f"{'device':<12} {'state':<11} {'coverage':<31} {'heading':>8} {'pitch':>6} {'roll':>7} "
            f"{'resid uT':>8} {'err deg':>7}  note"
        ),
    ]
    for device in sorted(views):
        v = views[device]
        note = ", ".join(v.missing) if v.state != "calibrated" else f"calibration {v.calibration_id}"
        if v.state != "calibrated" and v.reason and not v.missing:
            note = v.reason
        lines.append(
            f"{device:<12} {v.state:<11} {_bar(v.coverage):<31} {_fmt(v.true_heading_deg, '8.1f')} "
            f"{_fmt(v.pitch_deg, '6.1f')} {_fmt(v.roll_deg, '7.1f')} {_fmt(v.residual_ut, '8.2f')} "
            f"{_fmt(v.error_deg, '7.2f')}  {note[:60]}"
        )
    return lines


class Viewer:
    """Feeds DeviceViews from the messages and prints them (redrawn on a terminal, plain lines otherwise)."""

    def __init__(self, prefix: str, out: TextIO, tty: bool) -> None:
        self.prefix, self.out, self.tty = prefix, out, tty
        self.views: dict[str, DeviceView] = {}

    def view(self, device: str) -> DeviceView:
        return self.views.setdefault(device, DeviceView())

    def feed(self, kind: wire.Kind, payload: bytes) -> None:
        try:
            if kind is wire.Kind.RAW:
                batch = wire.decode_raw(payload)
                self.view(batch.device).on_raw(batch)
            elif kind is wire.Kind.HEADING:
                heading = wire.decode_heading(payload)
                self.view(heading.device).on_heading(heading)
            elif kind is wire.Kind.PROGRESS:
                message = wire.decode_progress(payload)
                self.view(message["device"]).on_progress(message)
            else:
                message = wire.unpack(payload)
                self.view(str(message.get("device"))).on_calibration(message)
        except (wire.WireError, KeyError, TypeError, ValueError):
            pass  # the services count malformed input; the view just skips it

    def show(self, elapsed_s: float) -> None:
        lines = render_lines(self.views, elapsed_s)
        if self.tty:
            self.out.write("\x1b[H\x1b[2J" + "\n".join(lines) + "\n")
        else:
            self.out.write("\n".join(lines) + "\n\n")
        self.out.flush()


def _start_services(
    settings: UpSettings, ports: dict[str, int], db: Path, logs: Path, dashboard: tuple[str, str] | None = None
) -> dict[str, Any]:
    common = ["--prefix", settings.prefix]
    commands = {
        "calibrator": [
            "calibrator",
            "--db",
            str(db),
            "--location",
            settings.location,
            *loopback_arguments(ports["calibrator"]),
        ],
        "compass": [
            "compass",
            "--location",
            settings.location,
            *loopback_arguments(ports["compass"], [ports["calibrator"]]),
        ],
        "edge": [
            "edge",
            "--emulate",
            "--devices",
            str(settings.devices),
            "--device",
            "dev",
            "--rate",
            str(settings.rate_hz),
            "--batch",
            str(settings.batch),
            "--speedup",
            str(settings.speedup),
            "--location",
            settings.location,
            *loopback_arguments(ports["edge"], [ports["calibrator"], ports["compass"]]),
        ],
    }
    if dashboard is not None:
        commands["dashboard"] = [
            "dashboard",
            "--http",
            dashboard[0],
            "--token",
            dashboard[1],
            "--location",
            settings.location,
            *loopback_arguments(ports["dashboard"], [ports[n] for n in SERVICES]),
        ]
    procs = {}
    for name in commands:
        with open(logs / f"{name}.log", "w") as log_file:  # the child keeps its own descriptor
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "services.cli", *commands[name], *common],
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
    return procs


def _stop_services(procs: dict[str, Any]) -> None:
    for proc in procs.values():
        if proc.poll() is None:
            proc.terminate()
    for proc in procs.values():
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _dashboard_http(settings: UpSettings, spare_port: int) -> tuple[str, str, str] | None:
    """(HOST:PORT, token, page address) of the dashboard: --http, else 127.0.0.1:8080, else a free port."""
    if not settings.dashboard:
        return None
    import secrets
    import socket

    from services.dashboard.service import DEFAULT_HTTP, page_address, parse_http

    http = settings.http
    if http is None:
        http = DEFAULT_HTTP
        with socket.socket() as sock:
            try:
                sock.bind(parse_http(DEFAULT_HTTP))
            except OSError:  # 8080 taken (another pipeline, another program): any free port will do
                http = f"127.0.0.1:{spare_port}"
    token = secrets.token_urlsafe(12)
    return http, token, page_address(*parse_http(http), token)


def _report_dead(dead: list[str], logs: Path) -> None:
    """Say which service stopped and show the end of its log (the logs go with the temporary directory)."""
    print(f"magnet up: {', '.join(dead)} stopped unexpectedly", file=sys.stderr)
    for name in dead:
        lines = (logs / f"{name}.log").read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:]
        print(f"--- end of the {name} log:\n" + "\n".join(lines), file=sys.stderr)


def _view_config(ports: dict[str, int]) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{ports["view"]}"]')
    conf.insert_json5("connect/endpoints", str([f"tcp/127.0.0.1:{ports[n]}" for n in SERVICES]).replace("'", '"'))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def _watch(settings: UpSettings, procs: dict[str, Any], ports: dict[str, int], logs: Path) -> int:
    """Show the view until --duration, a signal, or a service that stops (exit status 1)."""
    tty = sys.stdout.isatty() and os.environ.get("CI", "").lower() not in ("1", "true")
    interval = settings.interval_s or (0.5 if tty else 3.0)
    stop = stop_event()
    viewer = Viewer(settings.prefix, sys.stdout, tty)
    started = time.monotonic()
    status = 0
    with zenoh.open(_view_config(ports)) as session:
        subscribers = {
            kind: session.declare_subscriber(wire.key(settings.prefix, "*", kind), zenoh.handlers.RingChannel(4096))
            for kind in (wire.Kind.RAW, wire.Kind.HEADING, wire.Kind.PROGRESS, wire.Kind.CALIBRATION)
        }
        next_view = started + min(interval, 1.0)
        while not stop.is_set():
            now = time.monotonic()
            if settings.duration_s is not None and now - started >= settings.duration_s:
                break
            dead = [name for name, proc in procs.items() if proc.poll() is not None]
            if dead:
                _report_dead(dead, logs)
                status = 1
                break
            for kind, subscriber in subscribers.items():
                while (sample := subscriber.try_recv()) is not None:
                    viewer.feed(kind, payload_bytes(sample))
            if now >= next_view:
                viewer.show(now - started)
                next_view = now + interval
            time.sleep(0.02)
        viewer.show(time.monotonic() - started)
    return status


def up(settings: UpSettings) -> int:
    """Run the local pipeline; the temporary directory (logs, and the store unless --db) is removed at exit."""
    workdir = Path(tempfile.mkdtemp(prefix="magnet-up-"))
    try:
        db = settings.db or workdir / "calibrations.db"
        ports = dict(zip((*SERVICES, "view", "dashboard", "http"), free_ports(6)))
        dashboard = _dashboard_http(settings, ports.pop("http"))
        procs = _start_services(settings, ports, db, workdir, dashboard and dashboard[:2])
        try:
            print(
                f"magnet up: calibrator, compass and {settings.devices} emulated device(s) on 127.0.0.1 ports "
                f"{ports['calibrator']}, {ports['compass']}, {ports['edge']}; store {db}; logs in {workdir} "
                "(removed at exit)",
                flush=True,
            )
            if dashboard:
                print(f"magnet up: dashboard at {dashboard[2]}", flush=True)
            return _watch(settings, procs, ports, workdir)
        finally:
            _stop_services(procs)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def run(args: argparse.Namespace) -> int:
    return up(UpSettings.from_args(args))
