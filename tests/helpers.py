"""Helpers the tests share: the command line as a process, loopback options and free ports, services started and
stopped with their logs, and waiting for a condition (an answer, a liveliness token, a line of output) with a
timeout instead of sleeping a guessed time.

Import from a test module as ``from helpers import MAGNET, wait_for`` (pytest puts ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import pytest

from services.common.processes import stop_processes
from services.common.zenoh_session import free_ports

__all__ = [
    "MAGNET",
    "NO_SCOUT",
    "REPO_ROOT",
    "Processes",
    "connect_args",
    "emulated_edge",
    "free_ports",
    "listen_args",
    "liveliness_keys",
    "magnet_json",
    "replay_raw",
    "run_magnet",
    "wait_for",
    "wait_for_liveliness",
]

T = TypeVar("T")

REPO_ROOT = Path(__file__).resolve().parents[1]
#: the ``magnet`` command, run by this interpreter from the source tree
MAGNET = [sys.executable, "-m", "services.cli"]
NO_SCOUT = ["--no-multicast-scouting"]
POLL_S = 0.1


def listen_args(port: int) -> list[str]:
    """Options that make a service listen on 127.0.0.1:port only, with multicast scouting off."""
    return [*NO_SCOUT, "--listen", f"tcp/127.0.0.1:{port}"]


def connect_args(*ports: int) -> list[str]:
    """``--connect tcp/127.0.0.1:PORT`` for each port."""
    return [arg for port in ports for arg in ("--connect", f"tcp/127.0.0.1:{port}")]


def run_magnet(
    *args: str, timeout: float = 120, input: str | None = None, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """Run ``magnet ARGS...`` to its end; output captured as text."""
    return subprocess.run(
        [*MAGNET, *args], capture_output=True, text=True, timeout=timeout, input=input, cwd=cwd or REPO_ROOT
    )


def magnet_json(*args: str, timeout: float = 15) -> tuple[int, list[Any]]:
    """Run a remote tool that prints JSON lines: (exit status, the decoded lines)."""
    out = run_magnet(*args, timeout=timeout)
    return out.returncode, [json.loads(line) for line in out.stdout.splitlines() if line.strip()]


def wait_for(check: Callable[[], T], timeout_s: float, what: str) -> T:
    """Call ``check`` until it returns something true and return that; fail the test after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        result = check()
        if result:
            return result
        if time.monotonic() >= deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(POLL_S)


def _loopback_client_config(port: int) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def emulated_edge(device: str, rate_hz: int = 500, batch: int = 25, hard_iron: str = "12,-7,4") -> list[str]:
    """``magnet edge`` arguments of one emulated simulated sensor ``device`` at ``rate_hz``, ``batch`` samples a
    message (the listen and connect arguments to add), with ``hard_iron`` (uT X,Y,Z): a sensor that needs
    calibrating, since the gate accepts only a fit that beats no calibration by more than chance."""
    return [
        *("edge", "--device", device, "--sensor", "sim", "--emulate", "--hard-iron", hard_iron),
        *("--rate", str(rate_hz), "--batch", str(batch)),
    ]


def liveliness_keys(port: int, pattern: str = "magnet/@alive/**", timeout_s: float = 2.0) -> set[str]:
    """The liveliness tokens matching ``pattern`` seen now through a session connected to 127.0.0.1:port."""
    import zenoh

    with zenoh.open(_loopback_client_config(port)) as session:
        return {
            str(reply.ok.key_expr)
            for reply in session.liveliness().get(pattern, timeout=timeout_s)
            if reply.ok is not None
        }


def wait_for_liveliness(port: int, keys: Iterable[str], timeout_s: float = 20) -> set[str]:
    """Wait until every key in ``keys`` has a liveliness token visible at 127.0.0.1:port; return the keys seen.

    A liveliness subscriber (with the tokens already present) is told of each token as it appears: no polling.
    """
    import zenoh

    wanted, seen, found = set(keys), set(), threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            seen.add(str(sample.key_expr))
        if wanted <= seen:
            found.set()

    with zenoh.open(_loopback_client_config(port)) as session:
        session.liveliness().declare_subscriber("magnet/@alive/**", on_token, history=True)
        if not found.wait(timeout_s):
            pytest.fail(f"timed out after {timeout_s} s waiting for liveliness tokens {sorted(wanted - seen)}")
        return set(seen)


class Processes:
    """``magnet`` processes started by one test, each logging to ``tmp_path/NAME.log``; ``stop_all`` ends them."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self._logs = contextlib.ExitStack()

    def start(self, name: str, *args: str, cwd: Path | None = None) -> subprocess.Popen[bytes]:
        """``magnet ARGS...`` as ``name``, in ``cwd`` (the repository by default; a folder of its own stands for
        another host's working directory)."""
        # the log stays open while the process runs; stop_all closes it
        log = self._logs.enter_context(open(self.tmp_path / f"{name}.log", "w"))  # noqa: SIM115
        self.procs[name] = subprocess.Popen(
            [*MAGNET, *args], stdout=log, stderr=subprocess.STDOUT, cwd=cwd or REPO_ROOT
        )
        return self.procs[name]

    def start_services(self) -> tuple[int, int, int]:
        """A calibrator (its store ``cal.db`` in tmp_path) and a compass connected to it, each listening on a free
        port of 127.0.0.1; (calibrator port, compass port, a free port for the edge)."""
        cal_port, comp_port, edge_port = free_ports(3)
        self.start("calibrator", "calibrator", "--db", str(self.tmp_path / "cal.db"), *listen_args(cal_port))
        self.start("compass", "compass", *listen_args(comp_port), *connect_args(cal_port))
        return cal_port, comp_port, edge_port

    def alive(self, name: str) -> bool:
        return self.procs[name].poll() is None

    def log(self, name: str) -> str:
        return (self.tmp_path / f"{name}.log").read_text()

    def stop_all(self) -> None:
        """SIGTERM to every process still running, SIGKILL to any that has not ended 5 s later; logs closed."""
        stop_processes(self.procs.values())
        self._logs.close()


def replay_raw(path: Path, device: str, *args: str) -> tuple[list[Any], subprocess.CompletedProcess[str]]:
    """(the raw batches (``magnet.wire.RawBatch``) a ``magnet edge --replay path --device device *args`` process
    sends to a listening session on 127.0.0.1, in arrival order; the finished process, which must exit 0 within
    60 s)."""
    import zenoh

    from magnet import wire

    (port,) = free_ports(1)
    conf = zenoh.Config()
    for key, value in (("listen/endpoints", f'["tcp/127.0.0.1:{port}"]'), ("scouting/multicast/enabled", "false")):
        conf.insert_json5(key, value)
    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(f"magnet/{device}/raw", zenoh.handlers.FifoChannel(1024))
        edge = ["edge", "--replay", str(path), "--device", device, *args]
        out = subprocess.run(
            [*MAGNET, *edge, *listen_args(free_ports(1)[0]), "--connect", f"tcp/127.0.0.1:{port}"],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=REPO_ROOT,
        )
        assert out.returncode == 0, out.stderr
        batches = []
        while (sample := subscriber.try_recv()) is not None:
            batches.append(wire.decode_raw(sample.payload.to_bytes()))
    return batches, out


def fit_input_of(run: Any, rate_hz: float) -> Any:
    """The ``magnet.calibration.fit_input.FitInput`` of a simulated run (``magnet.simulator.simulate``): its field,
    accelerometer and gyroscope at ``rate_hz``, with the WMM's |B| (uT) and dip (deg) at its place as the priors."""
    from magnet.calibration.fit_input import FitInput

    return FitInput(
        run.mag_ut,
        acc=run.acc_ms2,
        gyr_rads=run.gyr_rads,
        period_s=1.0 / rate_hz,
        field_ut=run.earth.total_ut,
        dip_deg=run.earth.inclination_deg,
    )


class StatusQuery:
    """A Zenoh query as a status board answers it (``services.common.status_board``): the replies unpacked, the
    errors, whether it was dropped (finalized)."""

    def __init__(self) -> None:
        self.replies: list[tuple[str, dict[str, Any]]] = []
        self.errors: list[bytes] = []
        self.dropped = False

    def reply(self, key: str, payload: bytes) -> None:
        from magnet import wire

        self.replies.append((key, wire.unpack(payload)))

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(payload)

    def drop(self) -> None:
        self.dropped = True


def rss_mb() -> float:
    """This process's resident memory, MB (/proc/self/statm)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


def held_by_waiting_samples(
    publisher: Any, handler: Any, count: int, payload: bytes, pause_s: float
) -> tuple[int, float]:
    """Three rounds (the first warms the allocator's arenas up) of ``count`` puts of ``payload`` that wait in
    ``handler`` (a Zenoh channel its service's pump would drain), then drained: (samples taken in the last round, MB
    given back when they went). ``pause_s`` between puts lets the receiving side read them one batch at a time."""
    import gc

    from services.common.allocator import give_back_now

    taken, held_mb = 0, 0.0
    for _ in range(3):
        for _ in range(count):
            publisher.put(payload)
            time.sleep(pause_s)
        time.sleep(1.0)
        gc.collect()
        give_back_now()
        held_mb = rss_mb()
        taken = 0
        while handler.try_recv() is not None:
            taken += 1
        gc.collect()
        give_back_now()
        held_mb -= rss_mb()
    return taken, held_mb
