"""Where a running ``magnet up`` can be reached, in a per-user runtime file the client commands read.

Each ``magnet up`` writes a file of its own, ``$XDG_RUNTIME_DIR/magnet/up-<pid>.json`` (``~/.cache/magnet/`` where
that variable is not set; folder 0700, file 0600) with ``{"v": 1, "pid", "prefix", "connect": [endpoint, ...],
"ports": {service: port}, "dashboard": address without its token | null}`` and removes only that file at exit, so
several pipelines run side by side and none loses its file to another. A command given none of ``--connect``,
``--listen`` or ``--config`` (``use_local_pipeline``) reaches the newest pipeline whose process still runs, with
multicast scouting off (and takes its prefix when its own is the default), and names the others when there are
several. Files left by pipelines that died are ignored.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
from pathlib import Path
from typing import Any

from magnet.wire import DEFAULT_PREFIX, validate_prefix

log = logging.getLogger("magnet.endpoint")

MAX_FILE_BYTES = 16_384
#: at most this many runtime files are read when looking for a pipeline (newest first)
MAX_FILES_READ = 64


def runtime_dir() -> Path:
    """The per-user folder of the runtime files."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    return Path(base) / "magnet" if base else Path.home() / ".cache" / "magnet"


def runtime_file(pid: int | None = None) -> Path:
    """The runtime file of the ``magnet up`` with process id ``pid`` (default: this process)."""
    return runtime_dir() / f"up-{os.getpid() if pid is None else pid}.json"


def _newest_first(folder: Path) -> list[Path]:
    """The runtime files in ``folder``, newest first (a file that vanishes meanwhile is left out)."""
    dated = []
    for path in folder.glob("up-*.json"):
        with contextlib.suppress(OSError):
            dated.append((path.stat().st_mtime_ns, path))
    return [path for _, path in sorted(dated, reverse=True)[:MAX_FILES_READ]]


def running_pipelines() -> list[dict[str, Any]]:
    """The records of every ``magnet up`` of this user that still runs, newest first."""
    found = (read_runtime_file(path) for path in _newest_first(runtime_dir()))
    return [record for record in found if record is not None]


def connect_endpoints(ports: dict[str, int], services: tuple[str, ...]) -> list[str]:
    """The loopback endpoints of ``services`` (names in ``ports``), in that order."""
    return [f"tcp/127.0.0.1:{ports[name]}" for name in services]


def connect_line(endpoints: list[str]) -> str:
    """The options a tool run elsewhere on this machine (or in a script) gives to reach these endpoints."""
    return " ".join(["--no-multicast-scouting", *(f"--connect {e}" for e in endpoints)])


def write_runtime_file(
    prefix: str, endpoints: list[str], ports: dict[str, int], dashboard: str | None, path: Path | None = None
) -> Path:
    """Write the file (atomically, owner-only) and return its path."""
    path = path or runtime_file()
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    record = {
        "v": 1,
        "pid": os.getpid(),
        "prefix": prefix,
        "connect": endpoints,
        "ports": ports,
        "dashboard": dashboard,
    }
    temporary = path.with_suffix(f".{os.getpid()}.tmp")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        json.dump(record, out)
    os.replace(temporary, path)
    return path


def remove_runtime_file(path: Path | None = None) -> None:
    """Remove the file if this process wrote it (another ``magnet up`` may have replaced it since)."""
    path = path or runtime_file()
    record = read_runtime_file(path, check_alive=False)
    if record is not None and record.get("pid") == os.getpid():
        with contextlib.suppress(OSError):
            path.unlink()


def _alive(pid: Any) -> bool:
    if isinstance(pid, bool) or not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True


def read_runtime_file(path: Path | None = None, check_alive: bool = True) -> dict[str, Any] | None:
    """The file's record when it is there, well formed and (``check_alive``) its writer still runs; else None. Without
    ``path``: the newest running pipeline's record."""
    if path is None:
        running = running_pipelines()
        return running[0] if running else None
    try:
        if path.stat().st_size > MAX_FILE_BYTES:
            return None
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        return None
    if not isinstance(record, dict) or record.get("v") != 1:
        return None
    endpoints, prefix = record.get("connect"), record.get("prefix")
    if not isinstance(endpoints, list) or not endpoints or not all(isinstance(e, str) for e in endpoints):
        return None
    try:
        validate_prefix(str(prefix))
    except ValueError:
        return None
    if check_alive and not _alive(record.get("pid")):
        return None
    return record


def use_local_pipeline(args: argparse.Namespace, path: Path | None = None) -> bool:
    """Point a client command's Zenoh options at the running ``magnet up`` when none were given; True if it did."""
    if args.connect or args.listen or args.config:
        return False
    record = read_runtime_file(path)
    if record is None:
        return False
    others = [str(other["pid"]) for other in running_pipelines()[1:]] if path is None else []
    if others:
        log.warning(
            "several magnet up pipelines run; reaching the newest (process %s), not process(es) %s: give --connect "
            "to choose",
            record["pid"],
            ", ".join(others),
        )
    args.connect = list(record["connect"])
    args.no_multicast_scouting = True
    if args.prefix == DEFAULT_PREFIX:
        args.prefix = str(record["prefix"])
    log.info("reaching the magnet up of process %s at %s", record["pid"], ", ".join(args.connect))
    return True
