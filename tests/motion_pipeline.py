"""Helpers for the tests that run recordings in motion through the services: a calibrator and a compass on
loopback, ``magnet edge --replay`` publishing a CSV at a multiple of its pace, and the compass's headings collected
per device in the test process (a Zenoh subscriber), joined back to the CSV's rows by ``seq``.

Import from a test module as ``from motion_pipeline import Pipeline`` (pytest puts ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import json
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zenoh
from helpers import MAGNET, REPO_ROOT, Processes, connect_args, free_ports, listen_args, wait_for_liveliness

from magnet import wire

PREFIX = "magnet"


def _client_config(*ports: int) -> zenoh.Config:
    conf = zenoh.Config()
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{p}" for p in ports]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class Headings:
    """Every heading message the compass publishes, decoded and kept per device (Zenoh's thread appends)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.by_device: dict[str, list[wire.HeadingBatch]] = {}

    def on_sample(self, sample: zenoh.Sample) -> None:
        batch = wire.decode_heading(sample.payload.to_bytes())
        with self.lock:
            self.by_device.setdefault(batch.device, []).append(batch)

    def samples(self, device: str) -> int:
        with self.lock:
            return sum(len(b) for b in self.by_device.get(device, []))

    def batches(self, device: str) -> list[wire.HeadingBatch]:
        with self.lock:
            return sorted(self.by_device.get(device, []), key=lambda b: b.seq)


class Calibrations:
    """Calibration records of every device as the calibrator publishes them, and the one in force on request."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.by_device: dict[str, list[dict]] = {}

    def on_sample(self, sample: zenoh.Sample) -> None:
        record = wire.unpack(sample.payload.to_bytes())
        with self.lock:
            self.by_device.setdefault(str(record["device"]), []).append(record)

    def published(self, device: str) -> list[dict]:
        with self.lock:
            return list(self.by_device.get(device, []))

    def in_force(self, device: str) -> dict | None:
        """The last accepted record published for ``device``, else the calibrator's answer to a query, else None."""
        accepted = [r for r in self.published(device) if r.get("accepted")]
        if accepted:
            return accepted[-1]
        for reply in self.session.get(wire.key(PREFIX, device, wire.Kind.CALIBRATION), timeout=2.0):
            if reply.ok is not None:
                return dict(wire.unpack(reply.ok.payload.to_bytes()))
        return None


class Pipeline:
    """A calibrator (SQLite in ``tmp_path``) and a compass, each in its own process on 127.0.0.1 with multicast
    scouting off; ``compass_args`` go to the compass (``--location``, ``--date``)."""

    def __init__(self, procs: Processes, tmp_path: Path, calibrator_args: list[str], compass_args: list[str]) -> None:
        self.procs, self.tmp_path = procs, tmp_path
        self.cal_port, self.comp_port = free_ports(2)
        procs.start(
            "calibrator", "calibrator", "--db", str(tmp_path / "cal.db"), *calibrator_args, *listen_args(self.cal_port)
        )
        procs.start("compass", "compass", *compass_args, *listen_args(self.comp_port), *connect_args(self.cal_port))
        wait_for_liveliness(
            self.comp_port, {"magnet/@alive/calibrator/calibrator", "magnet/@alive/compass/compass"}, timeout_s=30
        )

    @contextmanager
    def headings(self) -> Iterator[Headings]:
        """Collect the compass's headings of every device while the block runs."""
        collected = Headings()
        with zenoh.open(_client_config(self.comp_port)) as session:
            session.declare_subscriber(wire.key(PREFIX, "*", wire.Kind.HEADING), collected.on_sample)
            yield collected

    @contextmanager
    def calibrations(self) -> Iterator[Calibrations]:
        """The calibration records the calibrator publishes while the block runs (as the compass gets them), and
        its answers to queries."""
        with zenoh.open(_client_config(self.cal_port)) as session:
            records = Calibrations(session)
            session.declare_subscriber(wire.key(PREFIX, "*", wire.Kind.CALIBRATION), records.on_sample)
            yield records

    def calibrate(self, calibrations: Calibrations, csv: Path, device: str, speed: float, batch: int) -> dict:
        """Replay ``csv`` (a tumble) for ``device`` until the calibrator puts a calibration in force, as an operator
        tumbles a device again when it was not enough (at most three times); the record."""
        for _ in range(3):
            self.replay(csv, device, speed, batch)
            deadline = time.monotonic() + 20.0
            while time.monotonic() < deadline:
                record = calibrations.in_force(device)
                if record is not None:
                    return record
                time.sleep(0.2)
        raise AssertionError(f"no calibration in force for {device}; calibrator log:\n{self.procs.log('calibrator')}")

    def _replay_args(self, csv: Path, device: str, speed: float, batch: int) -> list[str]:
        return [
            *MAGNET,
            "edge",
            "--replay",
            str(csv),
            "--device",
            device,
            "--speed",
            str(speed),
            "--batch",
            str(batch),
            *listen_args(free_ports(1)[0]),
            *connect_args(self.cal_port, self.comp_port),
        ]

    def replay(self, csv: Path, device: str, speed: float, batch: int, timeout_s: float = 120) -> dict:
        """``magnet edge --replay`` to its end, connected to both services; its summary line."""
        args = self._replay_args(csv, device, speed, batch)
        out = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, cwd=REPO_ROOT)
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout.strip().splitlines()[-1])

    def start_replay(self, csv: Path, device: str, speed: float, batch: int) -> subprocess.Popen[bytes]:
        """``magnet edge --replay`` started (several replays run at once), its output in ``tmp_path/edge-DEVICE.log``;
        stopped with the other processes."""
        return self.procs.start(f"edge-{device}", *self._replay_args(csv, device, speed, batch)[len(MAGNET) :])


#: the compass puts headings without blocking (a slow subscriber loses messages rather than slowing the compass):
#: on a loaded machine a few may not reach the test; at least this share must, and each one that does is checked
MIN_RECEIVED_SHARE = 0.8
#: no new heading for this long after the replay: the rest is not coming
QUIET_S = 3.0


def received(headings: Headings, device: str, published: int, batch: int, timeout_s: float) -> np.ndarray:
    """Wait for the compass's headings of ``published`` samples (batches of ``batch``) of ``device`` (the last
    batch's, or quiet for ``QUIET_S``), and return the row of the CSV of each heading received, in seq order (N,)
    (seq * batch + index). The compass may have missed the first batches if it joined late; from its first one on,
    at least ``MIN_RECEIVED_SHARE`` of the messages must arrive, each once."""
    last_seq = (published - 1) // batch
    deadline, count, changed = time.monotonic() + timeout_s, -1, time.monotonic()
    while True:
        batches = headings.batches(device)
        if batches and batches[-1].seq == last_seq:
            break
        if len(batches) != count:
            count, changed = len(batches), time.monotonic()
        elif count > 0 and time.monotonic() - changed > QUIET_S:
            break
        assert time.monotonic() < deadline, f"{device}: after {timeout_s} s, {count} heading messages"
        time.sleep(0.1)
    seqs = [b.seq for b in batches]
    assert len(seqs) == len(set(seqs)), f"{device}: heading messages repeated"
    expected = last_seq + 1 - seqs[0]
    assert len(seqs) >= MIN_RECEIVED_SHARE * expected, f"{device}: {len(seqs)} of {expected} heading messages"
    return np.concatenate([b.seq * batch + np.arange(len(b)) for b in batches])


def joined(headings: Headings, device: str, name: str) -> np.ndarray:
    """One field of every heading message of ``device``, in seq order, joined; a field of the whole message (such as
    ``calibration_id``) repeated for each of its samples."""
    batches = headings.batches(device)
    return np.concatenate(
        [
            np.broadcast_to(np.asarray(getattr(b, name)), (len(b),))
            if np.ndim(getattr(b, name)) == 0
            else np.asarray(getattr(b, name))
            for b in batches
        ]
    )
