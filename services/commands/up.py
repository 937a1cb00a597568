"""``magnet up``: the whole pipeline on this machine, with a live view.

N emulated devices (one ``magnet edge --emulate --devices N`` process: each device its own hard and soft iron), a
calibrator (SQLite in ``--db`` or a temporary directory) and a compass, each in its own process (started with
subprocess, before this process opens its own session), on 127.0.0.1 with explicit ports and multicast scouting off.
The view shows per device: calibration state and sphere coverage while collecting, then the true heading, pitch,
roll, the calibration residual, and the heading error against the simulator's truth. On a terminal it redraws in
place; without one (CI, pipes) it prints plain lines every few seconds. Ctrl-C (or ``--duration``) stops everything.

Modules: ``up_settings`` (the options, checked), ``up_processes`` (the child services), ``up_view`` (the view).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import zenoh

from magnet import wire
from services.commands.up_processes import SERVICES, dashboard_http, report_dead, start_services, stop_services
from services.commands.up_settings import MAX_DEVICES, UpSettings
from services.commands.up_view import DeviceView, Viewer, render_lines
from services.common.endpoint import connect_endpoints, connect_line, remove_runtime_file, write_runtime_file
from services.common.zenoh_session import drain, free_ports, payload_bytes, stop_event

__all__ = ["MAX_DEVICES", "DeviceView", "UpSettings", "Viewer", "add_arguments", "render_lines", "run", "up"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    UpSettings.add_arguments(parser)


def _view_config(ports: dict[str, int]) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("listen/endpoints", f'["tcp/127.0.0.1:{ports["view"]}"]')
    conf.insert_json5("connect/endpoints", str([f"tcp/127.0.0.1:{ports[n]}" for n in SERVICES]).replace("'", '"'))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def _watch(settings: UpSettings, procs: dict[str, subprocess.Popen[bytes]], ports: dict[str, int], logs: Path) -> int:
    """Show the view until --duration, a signal, or a service that stops (exit status 1)."""
    tty = sys.stdout.isatty() and os.environ.get("CI", "").lower() not in ("1", "true")
    interval = settings.interval_s or (0.5 if tty else 3.0)
    stop = stop_event()
    viewer = Viewer(settings.prefix, sys.stdout, tty)
    started = time.monotonic()
    status = 0
    with contextlib.ExitStack() as declared:
        session = declared.enter_context(zenoh.open(_view_config(ports)))
        subscribers = {
            kind: declared.enter_context(
                session.declare_subscriber(wire.key(settings.prefix, "*", kind), zenoh.handlers.RingChannel(4096))
            )
            for kind in (wire.Kind.RAW, wire.Kind.HEADING, wire.Kind.PROGRESS, wire.Kind.CALIBRATION, wire.Kind.ALERT)
        }
        in_force = session.get(wire.key(settings.prefix, "*", wire.Kind.CALIBRATION), timeout=3.0)  # stored ones
        next_view = started + min(interval, 1.0)
        try:
            while not stop.is_set():
                now = time.monotonic()
                if settings.duration_s is not None and now - started >= settings.duration_s:
                    break
                dead = [name for name, proc in procs.items() if proc.poll() is not None]
                if dead:
                    viewer.close()  # the live view ends before the report of what stopped
                    report_dead(dead, logs)
                    status = 1
                    break
                for kind, subscriber in subscribers.items():
                    while (sample := subscriber.try_recv()) is not None:
                        viewer.feed(kind, payload_bytes(sample))
                for reply in drain(in_force, 1000):
                    if reply.ok is not None:
                        viewer.feed(wire.Kind.CALIBRATION, payload_bytes(reply.ok))
                if now >= next_view:
                    viewer.show(now - started)
                    next_view = now + interval
                time.sleep(0.02)
            if status == 0:
                viewer.show(time.monotonic() - started)
        finally:
            viewer.close()  # the terminal gets its cursor back whatever happened
    return status


def _write_runtime(
    settings: UpSettings, endpoints: list[str], ports: dict[str, int], dashboard: tuple[str, str, str] | None
) -> Path | None:
    """The runtime file the client commands read (``services.common.endpoint``); None when it cannot be written."""
    page = dashboard[2].split("?", 1)[0] if dashboard else None
    try:
        return write_runtime_file(settings.prefix, endpoints, {n: ports[n] for n in SERVICES}, page)
    except OSError as exc:
        print(f"magnet up: cannot write the runtime file: {exc}", file=sys.stderr)
        return None


def up(settings: UpSettings) -> int:
    """Run the local pipeline; the temporary directory (logs, and the store unless --db) is removed at exit."""
    workdir = Path(tempfile.mkdtemp(prefix="magnet-up-"))
    try:
        db = settings.db or workdir / "calibrations.db"
        ports = dict(zip((*SERVICES, "view", "dashboard", "http"), free_ports(6)))
        dashboard = dashboard_http(settings, ports.pop("http"))
        procs = start_services(settings, ports, db, workdir, dashboard and dashboard[:2])
        endpoints = connect_endpoints(ports, SERVICES)
        try:
            labelled = ", ".join(f"{name} 127.0.0.1:{ports[name]}" for name in SERVICES)
            print(
                f"magnet up: {settings.devices} emulated device(s); Zenoh (TCP) ports: {labelled}; store {db}; "
                f"logs in {workdir} (removed at exit)",
                flush=True,
            )
            runtime = _write_runtime(settings, endpoints, ports, dashboard)
            print(
                "magnet up: other magnet commands of this user find this pipeline by themselves"
                + (f" ({runtime})" if runtime else "")
                + f"; from elsewhere on this machine give them: {connect_line(endpoints)}",
                flush=True,
            )
            if dashboard:
                print(f"magnet up: dashboard at {dashboard[2]}", flush=True)
            return _watch(settings, procs, ports, workdir)
        finally:
            remove_runtime_file()
            stop_services(procs)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)


def run(args: argparse.Namespace) -> int:
    return up(UpSettings.from_args(args))
