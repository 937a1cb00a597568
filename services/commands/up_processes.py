"""The child processes of ``magnet up``: the services started, stopped, and reported when they stop early."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from services.commands.up_settings import UpSettings
from services.common.processes import stop_processes
from services.common.zenoh_session import loopback_arguments

SERVICES = ("calibrator", "compass", "edge")
LOG_TAIL_LINES = 15


def start_services(
    settings: UpSettings, ports: dict[str, int], db: Path, logs: Path, dashboard: tuple[str, str] | None = None
) -> dict[str, subprocess.Popen[bytes]]:
    common = ["--prefix", settings.prefix]
    commands = {
        "calibrator": [
            "calibrator",
            "--db",
            str(db),
            f"--location={settings.location}",
            *loopback_arguments(ports["calibrator"]),
        ],
        "compass": [
            "compass",
            f"--location={settings.location}",
            *settings.drift_arguments(),
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
            f"--location={settings.location}",
            *loopback_arguments(ports["edge"], [ports["calibrator"], ports["compass"]]),
        ],
    }
    if dashboard is not None:
        commands["dashboard"] = [
            "dashboard",
            "--http",
            dashboard[0],
            f"--token={dashboard[1]}",
            f"--location={settings.location}",
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


def stop_services(procs: dict[str, subprocess.Popen[bytes]]) -> None:
    stop_processes(procs.values())


def dashboard_http(settings: UpSettings, spare_port: int) -> tuple[str, str, str] | None:
    """(HOST:PORT, token, page address) of the dashboard: --http, else 127.0.0.1:8080, else a free port."""
    if not settings.dashboard:
        return None
    import secrets

    from services.dashboard.service import page_address
    from services.dashboard.settings import DEFAULT_HTTP, bindable, parse_http

    http = settings.http
    if http is None:  # 8080 unless taken (another pipeline, another program): then any free port will do
        http = DEFAULT_HTTP if bindable(DEFAULT_HTTP) else f"127.0.0.1:{spare_port}"
    token = secrets.token_urlsafe(12)
    return http, token, page_address(*parse_http(http), token)


def report_dead(dead: list[str], logs: Path) -> None:
    """Say which service stopped and show the end of its log (the logs go with the temporary directory)."""
    print(f"magnet up: {', '.join(dead)} stopped unexpectedly", file=sys.stderr)
    for name in dead:
        lines = (logs / f"{name}.log").read_text(errors="replace").splitlines()[-LOG_TAIL_LINES:]
        print(f"--- end of the {name} log:\n" + "\n".join(lines), file=sys.stderr)
