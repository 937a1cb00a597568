"""Helpers for the tests that run recordings in motion through the services: a calibrator and a compass on
loopback, ``magnet edge --replay`` publishing a CSV at a multiple of its pace, and the compass's headings collected
per device in the test process (a Zenoh subscriber), joined back to the CSV's rows by ``seq``.

Import from a test module as ``from motion_pipeline import Pipeline`` (pytest puts ``tests/`` on ``sys.path``).
"""

from __future__ import annotations

import json
import subprocess
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import zenoh
from helpers import MAGNET, REPO_ROOT, Processes, connect_args, free_ports, listen_args, wait_for, wait_for_liveliness

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
    def calibrations(self) -> Iterator[dict[str, list[dict]]]:
        """The calibration records the calibrator publishes while the block runs, per device (as the compass gets
        them)."""
        records: dict[str, list[dict]] = {}

        def on_sample(sample: zenoh.Sample) -> None:
            record = wire.unpack(sample.payload.to_bytes())
            records.setdefault(str(record["device"]), []).append(record)

        with zenoh.open(_client_config(self.cal_port)) as session:
            session.declare_subscriber(wire.key(PREFIX, "*", wire.Kind.CALIBRATION), on_sample)
            yield records

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


def received(headings: Headings, device: str, published: int, batch: int, timeout_s: float) -> np.ndarray:
    """Wait for the compass's headings of ``published`` samples (batches of ``batch``) of ``device``, and return the
    row of the CSV each heading belongs to (N,) (seq * batch + index): the compass may have missed the first batches
    if it joined late, but from its first batch on it must have every one, in order, once."""
    last_seq = (published - 1) // batch

    def arrived() -> bool:
        batches = headings.batches(device)
        return bool(batches) and batches[-1].seq == last_seq

    wait_for(arrived, timeout_s, f"the compass's heading of {device}'s last batch (seq {last_seq})")
    seqs = [b.seq for b in headings.batches(device)]
    missing = sorted(set(range(seqs[0], last_seq + 1)) - set(seqs))
    assert not missing and len(seqs) == len(set(seqs)), f"{device}: from seq {seqs[0]} on, missing {missing[:10]}"
    return np.arange(seqs[0] * batch, published)


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
