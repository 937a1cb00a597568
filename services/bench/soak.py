"""``magnet bench soak --minutes N``: the local pipeline under a schedule of faults, then its figures.

The pipeline of a deployment on loopback: a router (``magnet router`` on 127.0.0.1), and as its clients a
calibrator, a compass (``--ros2`` too), an edge with 10 simulated devices (a new set of ids each time the edge is
restarted, so calibrations keep being made), an edge reading MAVLink on a UDP port (``mavedge``: a real vehicle
sends to it throughout, ``services.bench.front_loads``) and a dashboard. The faults (``services.bench.soak_plan``):
kill -9 of each service and its restart,
a router restart, a flood of new device ids (``services.bench.flood``), msgpack bombs (4 MB) on a raw key, and a full
disk under the calibrator's database: a tmpfs it mounts when it can (running as root), filled for a few seconds
(otherwise skipped, and said so). It watches headings and calibrations as a client of the router, the services'
status every 2 s and their memory (/proc) every 0.5 s; a service above ``RSS_CAP_MB`` is killed and restarted (and
reported) so that a soak cannot take the machine. Bounded in time; everything under a temporary directory.
"""

from __future__ import annotations

import contextlib
import json
import logging
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
from services.bench.soak_disk import FullDisk
from services.bench.soak_plan import (
    MAV_FLOOD_COUNT,
    RESTART_GRACE_S,
    STREAMS,
    STREAMS_HOLD_S,
    DropTotals,
    Fault,
    HeadingGaps,
    MemoryWatch,
    StatusTimes,
    front_lines,
    report,
    round_of,
    schedule,
)
from services.common.processes import stop_processes
from services.common.zenoh_session import ZenohSettings, free_ports, open_session, payload_bytes

log = logging.getLogger("magnet.bench.soak")

PREFIX = wire.DEFAULT_PREFIX
LOCATION = DEFAULT_LOCATION
SERVICES = ("router", "calibrator", "compass", "edge", "mavedge", "dashboard")
#: the status names of the services that answer one (the edge's: its --device of this run)
STATUS_NAMES = {"calibrator": "calibrator", "compass": "compass", "mavedge": "edge-mavedge"}
REAL_VEHICLE = "mav1-mag1"  # the vehicle front_loads sends throughout (system id 1, SCALED_IMU2)
DEVICES = 10
RSS_CAP_MB = 1500.0
BOMBS, BOMB_BYTES = 20, 4_000_000
FLOOD_COUNT, FLOOD_RATE = 20_000, 5_000.0
#: the calibrator, compass and dashboard are sized for this many devices (--max-devices): the first flood of ids fills
#: their tables, so later rounds show growth, not a bound still filling (at the default 10,000 the calibrator fills it
#: only in a fourth flood, admitting about 3,000 ids a flood; the dashboard had 6,582 rows after the first, 10,000 after
#: the second: its headings wait in a ring of 1,024 a tick)
MAX_DEVICES = 2_000


class Pipeline:
    """The services as child processes (logs in ``workdir``), each restartable; ``runs[name]`` counts its starts."""

    def __init__(self, workdir: Path, db_dir: Path, port: int) -> None:
        self.workdir, self.db_dir, self.port = workdir, db_dir, port
        self.mav_port, self.http_port = free_ports(2)
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.runs = dict.fromkeys(SERVICES, 0)
        self.started: dict[str, float] = {}
        self.helpers: list[subprocess.Popen[bytes]] = []

    def command(self, name: str) -> list[str]:
        client = ["--mode", "client", "--connect", f"tcp/127.0.0.1:{self.port}", "--no-multicast-scouting"]
        place = f"--location={LOCATION}"
        sized = [place, "--max-devices", str(MAX_DEVICES)]
        return {
            "router": ["router", "--listen", f"tcp/127.0.0.1:{self.port}", "--no-multicast-scouting"],
            "calibrator": ["calibrator", "--db", str(self.db_dir / "c.db"), *sized, *client],
            "compass": ["compass", *sized, "--ros2", *client],
            "mavedge": ["edge", "--mavlink", f"udpin:127.0.0.1:{self.mav_port}", "--device", "mavedge", *client],
            "dashboard": ["dashboard", "--http", f"127.0.0.1:{self.http_port}", "--token", "soak", *sized, *client],
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
        self.started[name] = time.monotonic()

    def in_grace(self, name: str, now: float) -> bool:
        """Whether ``name`` or the router started within ``RESTART_GRACE_S``."""
        return any(now - self.started.get(n, -1e9) < RESTART_GRACE_S for n in (name, "router"))

    def kill9(self, name: str) -> None:
        """kill -9, then start it again."""
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        self.start(name)

    def helper(self, *args: str, module: str = "flood", port: int | None = None) -> None:
        """A hostile load process (``services.bench.<module>``), left running; its JSON line in ``helper-N.json``."""
        with open(self.workdir / f"helper-{len(self.helpers)}-{args[0]}.json", "w") as out:
            self.helpers.append(
                subprocess.Popen(
                    [sys.executable, "-m", f"services.bench.{module}", *args, "--port", str(port or self.port)],
                    stdout=out,
                    stderr=subprocess.DEVNULL,
                )
            )

    def stop_all(self) -> None:
        stop_processes([*self.helpers, *self.procs.values()])


class Observer:
    """A client of the router: headings (gaps), calibrations published, status answers (drops). ``asking``: the
    session the status queries go on, one with no subscribers: on ``session`` an answer came behind the headings
    this process takes (up to 20,000 in seconds during a flood, each a Python callback) on the same link."""

    def __init__(self, session: zenoh.Session, asking: zenoh.Session | None = None) -> None:
        self.session, self.asking = session, asking or session
        self.gaps = HeadingGaps()
        self.published: dict[str, int] = {}
        self.fault = ""
        self.vehicle_gap_s, self.vehicle_headings, self._vehicle_last = 0.0, 0, 0.0
        self.lock = threading.Lock()
        self.declared = contextlib.ExitStack()
        for kind, handler in ((wire.Kind.HEADING, self._on_heading), (wire.Kind.CALIBRATION, self._on_calibration)):
            self.declared.enter_context(session.declare_subscriber(wire.key(PREFIX, "*", kind), handler))

    def __enter__(self) -> Observer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.declared.close()

    def _on_heading(self, sample: zenoh.Sample) -> None:
        device, now = str(sample.key_expr).rsplit("/", 2)[-2], time.monotonic()
        with self.lock:
            if not device.startswith("mav") or device == REAL_VEHICLE:  # the MAVLink flood's ids recur each flood
                self.gaps.on_heading(device, now, self.fault)
            if device == REAL_VEHICLE:
                if self.vehicle_headings:
                    self.vehicle_gap_s = max(self.vehicle_gap_s, now - self._vehicle_last)
                self.vehicle_headings, self._vehicle_last = self.vehicle_headings + 1, now

    def _on_calibration(self, sample: zenoh.Sample) -> None:
        try:
            record = wire.decode_calibration(payload_bytes(sample))
        except wire.WireError:
            return
        with self.lock:
            self.published[record.device] = max(self.published.get(record.device, -1), int(record.created_ns))

    def status(self, name: str) -> dict[str, Any] | None:
        for reply in self.asking.get(wire.status_key(PREFIX, name), timeout=1.0):
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
        self.memory, self.drops, self.status_times = MemoryWatch(), DropTotals(), StatusTimes()
        self.done: list[str] = []
        self.notes: list[str] = []
        self.last: dict[str, dict[str, Any]] = {}  # each service's last status answer
        self.deleted = {"times": 0, "with_file": 0, "while_gone": 0, "gone_seen": 0, "seen_after_s": 0.0}
        self.delete_at: float | None = None
        self.started = time.monotonic()

    def run(self) -> str:
        for name in SERVICES:
            self.pipeline.start(name)
        seconds = str(self.minutes * 60.0)
        self.pipeline.helper("vehicle", "--seconds", seconds, module="front_loads", port=self.pipeline.mav_port)
        time.sleep(1.0)
        client = ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{self.port}",), no_multicast_scouting=True)
        try:
            with open_session(client) as session, open_session(client) as asking, Observer(session, asking) as observer:
                self._loop(observer)
                served = observer.served()
        finally:
            self.pipeline.stop_all()
            self.disk.unmount()
        text = report(self.minutes, self.done, observer.published, served, observer.gaps, self.memory, self.drops)
        return "\n".join([text, *self.status_times.lines(), *self._front_lines(observer), *self.notes])

    def _loop(self, observer: Observer) -> None:
        pending, end = list(self.faults), self.started + self.minutes * 60.0
        next_memory = next_status = 0.0
        release: tuple[float, str] | None = None
        while (now := time.monotonic()) < end:
            elapsed = now - self.started
            if now >= next_memory:
                next_memory = now + 0.5
                self._sample_memory(round_of(len(self.done)), observer.fault or "warm-up")
            if pending and elapsed >= pending[0].at_s:
                fault = pending.pop(0)
                observer.fault = fault.label
                release = self._inflict(fault, now, observer) or release
            if release is not None and now >= release[0]:
                self._release(release[1], observer)
                release = None
            if now >= next_status:
                next_status = now + 2.0
                self._poll_status(observer)
            time.sleep(0.1)
        if release is not None:
            self._release(release[1], observer)
        self._poll_status(observer)

    def _release(self, kind: str, observer: Observer) -> None:
        """The end of a held fault: the disk freed, or the calibrator of a deleted database restarted."""
        if kind == "full-disk":
            self.disk.free()
            return
        with observer.lock:  # calibrations published while the store was gone: into the deleted file
            self.deleted["while_gone"] += len(observer.published)
        self.pipeline.kill9("calibrator")  # what an operator does: restart it on a new file
        self.delete_at = None
        with observer.lock:
            observer.published.clear()  # judged from the new file on

    def _inflict(self, fault: Fault, now: float, observer: Observer) -> tuple[float, str] | None:
        """Start ``fault``; (when to end it, its kind) for a fault held a while."""
        log.info("%.0f s: %s", now - self.started, fault.label)
        self.done.append(fault.label)
        if fault.kind in ("kill", "router"):
            self.pipeline.kill9(fault.target or "router")
        elif fault.kind == "bombs":  # and 2,000 dashboard event streams
            self.pipeline.helper("bombs", "--count", str(BOMBS), "--size", str(BOMB_BYTES), "--device", "s0-000")
            http = f"127.0.0.1:{self.pipeline.http_port}"
            args = ("--count", str(STREAMS), "--seconds", str(STREAMS_HOLD_S), "--http", http)
            self.pipeline.helper("streams", *args, module="front_loads")
        elif fault.kind == "flood":  # of ids on Zenoh (the compass's ROS 2 side too) and on the MAVLink port
            start = FLOOD_COUNT * self.done.count("flood")
            self.pipeline.helper("ids", "--count", str(FLOOD_COUNT), "--rate", str(FLOOD_RATE), "--start", str(start))
            count = str(MAV_FLOOD_COUNT)
            self.pipeline.helper("mavlink", "--count", count, module="front_loads", port=self.pipeline.mav_port)
        elif fault.kind == "delete-db":
            for suffix in ("", "-wal", "-shm"):
                (self.disk.directory / f"c.db{suffix}").unlink(missing_ok=True)
            with observer.lock:
                self.deleted["with_file"] += len(observer.published)
                observer.published.clear()  # what was stored went with the file; judged from here on
            self.deleted["times"] += 1
            self.delete_at = now
            return now + fault.hold_s, "delete-db"
        elif fault.kind == "full-disk":
            if not self.disk.mounted:
                self.done[-1] = "full-disk (skipped)"
                self._note(f"full disk skipped: {self.disk.why_not}")
                return None
            written = self.disk.fill()
            self._note(f"full disk: {written >> 20} MB written to fill the tmpfs, held {fault.hold_s:g} s")
            return now + fault.hold_s, "full-disk"
        return None

    def _note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)

    def _sample_memory(self, round_no: int, fault: str | None) -> None:
        for name, proc in self.pipeline.procs.items():
            rss = rss_mb(proc.pid) if proc.poll() is None else None
            self.memory.sample(name, rss, round_no, fault, t_s=time.monotonic() - self.started)
            if rss is not None and rss > RSS_CAP_MB:
                self._note(f"{name} killed and restarted by the soak at {rss:.0f} MB (cap {RSS_CAP_MB:g} MB)")
                self.pipeline.kill9(name)

    def _poll_status(self, observer: Observer) -> None:
        names = {**STATUS_NAMES, "edge": f"edge-s{self.pipeline.runs['edge'] - 1}"}
        for service, name in names.items():
            asked = time.monotonic()
            answer = observer.status(name)
            took = time.monotonic() - asked
            grace = self.pipeline.in_grace(service, asked)
            self.status_times.add(service, None if answer is None else took, grace, observer.fault or "warm-up")
            if answer is None:
                continue
            self.last[service] = answer
            dropped = dict(answer.get("dropped") or {})
            reads = answer.get("reads")
            if isinstance(reads, dict) and isinstance(reads.get("dropped"), dict):
                dropped.update({f"reads:{k}": v for k, v in reads["dropped"].items()})
            self.drops.update(service, self.pipeline.runs[service], dropped)
            if service == "calibrator" and answer.get("store") == "gone" and self.delete_at is not None:
                self.deleted["gone_seen"] += 1
                self.deleted["seen_after_s"] = max(self.deleted["seen_after_s"], asked - self.delete_at)
                self.delete_at = None  # seen for this deletion

    def _front_lines(self, observer: Observer) -> list[str]:
        """The figures of the front door's faults (``soak_plan.front_lines``), from the helpers' JSON lines."""
        results: dict[str, list[dict[str, Any]]] = {}
        for path in sorted(self.pipeline.workdir.glob("helper-*.json")):
            with contextlib.suppress(OSError, ValueError):
                if text := path.read_text().strip():
                    results.setdefault(path.stem.split("-", 2)[2], []).append(json.loads(text.splitlines()[-1]))
        vehicle = (REAL_VEHICLE, observer.vehicle_gap_s, observer.vehicle_headings)
        return front_lines(self.last, results, self.deleted, vehicle)


def run_soak_benchmark(minutes: float = 10.0, samples: str | None = None) -> str:
    """Run the soak for ``minutes``; the figures as text. ``samples``: a file for every RSS sample (JSON: service ->
    [[t_s, round, MB], ...]), to judge the memory again afterwards."""
    with tempfile.TemporaryDirectory(prefix="magnet-soak-") as workdir:
        soak = Soak(minutes, Path(workdir))
        text = soak.run()
    if samples:
        series = {name: m.samples for name, m in soak.memory.services.items()}
        Path(samples).write_text(json.dumps(series))
    return text
