"""``magnet bench soak --minutes N``: the local pipeline under a schedule of faults, then its figures.

The pipeline of a deployment on loopback: a router (``magnet router`` on 127.0.0.1), and as its clients a
calibrator, a compass and an edge with 10 simulated devices (a new set of ids each time the edge is restarted, so
calibrations keep being made). The faults (``services.bench.soak_plan``): kill -9 of each service and its restart,
a router restart, msgpack bombs (4 MB) on a raw key, a flood of new device ids (``services.bench.flood``), and a full
disk under the calibrator's database: a tmpfs it mounts when it can (running as root), filled for a few seconds
(otherwise skipped, and said so). It watches headings and calibrations as a client of the router, the services'
status every 2 s and their memory (/proc) every 0.5 s; a service above ``RSS_CAP_MB`` is killed and restarted (and
reported) so that a soak cannot take the machine. Bounded in time; everything under a temporary directory.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from magnet import wire
from magnet.simulator import DEFAULT_LOCATION
from services.bench.flood import rss_mb
from services.bench.soak_plan import DropTotals, Fault, HeadingGaps, MemoryWatch, report, round_of, schedule
from services.common.processes import stop_processes
from services.common.zenoh_session import ZenohSettings, free_ports, open_session, payload_bytes

log = logging.getLogger("magnet.bench.soak")

PREFIX = wire.DEFAULT_PREFIX
LOCATION = DEFAULT_LOCATION
SERVICES = ("router", "calibrator", "compass", "edge")
DEVICES = 10
RSS_CAP_MB = 1500.0
TMPFS_SIZE = "16m"
BOMBS, BOMB_BYTES = 20, 4_000_000
FLOOD_COUNT, FLOOD_RATE = 20_000, 5_000.0
#: the calibrator and compass are sized for this many devices (--max-devices): the first flood of ids fills their
#: tables, so what the later rounds add is growth, not a bound still filling (at the default 10,000 the calibrator,
#: admitting about 3,000 new ids a flood at --enrol-rate 200/s, fills it only in a fourth flood)
MAX_DEVICES = 2_000


class Pipeline:
    """The services as child processes (logs in ``workdir``), each restartable; ``runs[name]`` counts its starts."""

    def __init__(self, workdir: Path, db_dir: Path, port: int) -> None:
        self.workdir, self.db_dir, self.port = workdir, db_dir, port
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.runs = dict.fromkeys(SERVICES, 0)
        self.helpers: list[subprocess.Popen[bytes]] = []

    def command(self, name: str) -> list[str]:
        client = ["--mode", "client", "--connect", f"tcp/127.0.0.1:{self.port}", "--no-multicast-scouting"]
        place = f"--location={LOCATION}"
        sized = ["--max-devices", str(MAX_DEVICES)]
        return {
            "router": ["router", "--listen", f"tcp/127.0.0.1:{self.port}", "--no-multicast-scouting"],
            "calibrator": ["calibrator", "--db", str(self.db_dir / "c.db"), place, *sized, *client],
            "compass": ["compass", place, *sized, *client],
            "edge": [
                *("edge", "--emulate", "--devices", str(DEVICES), "--device", f"s{self.runs['edge']}", place),
                *("--rate", "50", "--batch", "10", "--speedup", "4", *client),
            ],
        }[name]

    def start(self, name: str) -> None:
        with open(self.workdir / f"{name}.log", "a") as log_file:
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", "services.cli", *self.command(name)],
                stdin=subprocess.DEVNULL,
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        self.runs[name] += 1

    def kill9(self, name: str) -> None:
        """kill -9, then start it again."""
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        self.start(name)

    def helper(self, *args: str) -> None:
        """A hostile load process (``services.bench.flood``), left running."""
        self.helpers.append(
            subprocess.Popen(
                [sys.executable, "-m", "services.bench.flood", *args, "--port", str(self.port)],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )

    def stop_all(self) -> None:
        stop_processes([*self.helpers, *self.procs.values()])


class FullDisk:
    """A small tmpfs under the calibrator's database when this process may mount one; ``fill`` and ``free``."""

    def __init__(self, directory: Path) -> None:
        self.directory, self.filler = directory, directory / "filler"
        self.mounted, self.why_not = False, ""
        directory.mkdir(parents=True, exist_ok=True)
        if os.geteuid() != 0:
            self.why_not = "needs root to mount a tmpfs"
            return
        done = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={TMPFS_SIZE}", "tmpfs", str(directory)],
            capture_output=True,
            text=True,
        )
        self.mounted = done.returncode == 0
        self.why_not = "" if self.mounted else f"mount failed: {done.stderr.strip()}"

    def fill(self) -> int:
        """Write until the filesystem is full; the bytes written."""
        written, chunk = 0, b"\0" * (1 << 20)
        with open(self.filler, "wb") as handle, contextlib.suppress(OSError):
            while written < (1 << 30):
                handle.write(chunk)
                handle.flush()
                written += len(chunk)
        with contextlib.suppress(OSError), open(self.filler, "ab") as handle:  # the last partial block
            while True:
                handle.write(b"\0" * 4096)
                handle.flush()
        return written

    def free(self) -> None:
        self.filler.unlink(missing_ok=True)

    def unmount(self) -> None:
        if self.mounted:
            done = subprocess.run(["umount", str(self.directory)], capture_output=True)
            if done.returncode != 0:
                subprocess.run(["umount", "-l", str(self.directory)], capture_output=True)
            self.mounted = False


class Observer:
    """A client of the router: headings (gaps), calibrations published, status answers (drops)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.gaps = HeadingGaps()
        self.published: dict[str, int] = {}
        self.fault = ""
        self.lock = threading.Lock()
        self.declared = contextlib.ExitStack()
        for kind, handler in ((wire.Kind.HEADING, self._on_heading), (wire.Kind.CALIBRATION, self._on_calibration)):
            self.declared.enter_context(session.declare_subscriber(wire.key(PREFIX, "*", kind), handler))

    def __enter__(self) -> Observer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.declared.close()

    def _on_heading(self, sample: zenoh.Sample) -> None:
        device = str(sample.key_expr).rsplit("/", 2)[-2]
        with self.lock:
            self.gaps.on_heading(device, time.monotonic(), self.fault)

    def _on_calibration(self, sample: zenoh.Sample) -> None:
        try:
            record = wire.decode_calibration(payload_bytes(sample))
        except wire.WireError:
            return
        with self.lock:
            self.published[record.device] = max(self.published.get(record.device, -1), int(record.created_ns))

    def status(self, name: str) -> dict[str, Any] | None:
        for reply in self.session.get(wire.status_key(PREFIX, name), timeout=1.0):
            if reply.ok is not None:
                try:
                    answer = wire.unpack(payload_bytes(reply.ok))
                except wire.WireError:
                    return None
                return answer if isinstance(answer, dict) else None
        return None

    def served(self) -> dict[str, int]:
        """device -> created_ns of every calibration the calibrator serves now."""
        out: dict[str, int] = {}
        for reply in self.session.get(wire.key(PREFIX, "*", wire.Kind.CALIBRATION), timeout=5.0):
            if reply.ok is not None:
                with contextlib.suppress(wire.WireError):
                    record = wire.decode_calibration(payload_bytes(reply.ok))
                    out[record.device] = int(record.created_ns)
        return out


class Soak:
    """One soak: the pipeline, the schedule, the watches; ``run`` returns the report."""

    def __init__(self, minutes: float, workdir: Path) -> None:
        self.minutes, self.faults = minutes, schedule(minutes)
        (self.port,) = free_ports(1)
        self.disk = FullDisk(workdir / "db")
        self.pipeline = Pipeline(workdir, self.disk.directory, self.port)
        self.memory, self.drops = MemoryWatch(), DropTotals()
        self.done: list[str] = []
        self.notes: list[str] = []
        self.started = time.monotonic()

    def run(self) -> str:
        for name in SERVICES:
            self.pipeline.start(name)
        time.sleep(1.0)
        client = ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{self.port}",), no_multicast_scouting=True)
        try:
            with open_session(client) as session, Observer(session) as observer:
                self._loop(observer)
                served = observer.served()
        finally:
            self.pipeline.stop_all()
            self.disk.unmount()
        text = report(self.minutes, self.done, observer.published, served, observer.gaps, self.memory, self.drops)
        return "\n".join([text, *self.notes])

    def _loop(self, observer: Observer) -> None:
        pending, end = list(self.faults), self.started + self.minutes * 60.0
        next_memory = next_status = 0.0
        release: float | None = None
        while (now := time.monotonic()) < end:
            elapsed = now - self.started
            if now >= next_memory:
                next_memory = now + 0.5
                self._sample_memory(round_of(len(self.done)), observer.fault or "warm-up")
            if pending and elapsed >= pending[0].at_s:
                fault = pending.pop(0)
                observer.fault = fault.label
                release = self._inflict(fault, now) or release
            if release is not None and now >= release:
                self.disk.free()
                release = None
            if now >= next_status:
                next_status = now + 2.0
                self._poll_status(observer)
            time.sleep(0.1)
        if release is not None:
            self.disk.free()
        self._poll_status(observer)

    def _inflict(self, fault: Fault, now: float) -> float | None:
        """Start ``fault``; the time to free the disk again for a full disk."""
        log.info("%.0f s: %s", now - self.started, fault.label)
        self.done.append(fault.label)
        if fault.kind == "kill":
            self.pipeline.kill9(fault.target)
        elif fault.kind == "router":
            self.pipeline.kill9("router")
        elif fault.kind == "bombs":
            self.pipeline.helper("bombs", "--count", str(BOMBS), "--size", str(BOMB_BYTES), "--device", "s0-000")
        elif fault.kind == "flood":
            start = FLOOD_COUNT * self.done.count("flood")
            self.pipeline.helper("ids", "--count", str(FLOOD_COUNT), "--rate", str(FLOOD_RATE), "--start", str(start))
        elif fault.kind == "full-disk":
            if not self.disk.mounted:
                self.done[-1] = "full-disk (skipped)"
                self._note(f"full disk skipped: {self.disk.why_not}")
                return None
            written = self.disk.fill()
            self._note(f"full disk: {written >> 20} MB written to fill the tmpfs, held {fault.hold_s:g} s")
            return now + fault.hold_s
        return None

    def _note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)

    def _sample_memory(self, round_no: int, fault: str | None) -> None:
        for name, proc in self.pipeline.procs.items():
            rss = rss_mb(proc.pid) if proc.poll() is None else None
            self.memory.sample(name, rss, round_no, fault)
            if rss is not None and rss > RSS_CAP_MB:
                self._note(f"{name} killed and restarted by the soak at {rss:.0f} MB (cap {RSS_CAP_MB:g} MB)")
                self.pipeline.kill9(name)

    def _poll_status(self, observer: Observer) -> None:
        names = {"calibrator": "calibrator", "compass": "compass", "edge": f"edge-s{self.pipeline.runs['edge'] - 1}"}
        for service, name in names.items():
            answer = observer.status(name)
            if answer is not None and isinstance(answer.get("dropped"), dict):
                self.drops.update(service, self.pipeline.runs[service], answer["dropped"])


def run_soak_benchmark(minutes: float = 10.0) -> str:
    """Run the soak for ``minutes``; the figures as text."""
    with tempfile.TemporaryDirectory(prefix="magnet-soak-") as workdir:
        return Soak(minutes, Path(workdir)).run()
