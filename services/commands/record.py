"""``magnet record --out FILE.mcap [--devices KEYEXPR] [--seconds N]``: record the fleet's raw samples, headings,
calibrations and alerts as ROS 2 messages with their schemas, in a rosbag2 (rosbags' writer, MCAP storage), so
Foxglove and ``ros2 bag`` open it and ``magnet fit/heading/report/edge --replay --topic`` read it back.

``--out NAME.mcap`` leaves one MCAP file; any other name leaves a rosbag2 directory (``metadata.yaml`` and the
``.mcap``). The topics are listed in ``magnet.ros2.recording``. The calibrations in force when it starts are asked
for and recorded first (their replies are taken as they come, while the recording runs). Messages that do not decode
are skipped and counted; the summary line says how many of each were written. Given no Zenoh options it records the
running ``magnet up`` (``services.common.endpoint``). A recording that heard nothing is an error (exit 1), and its
empty bag is not left behind.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import shutil
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import zenoh
from rosbags.rosbag2 import StoragePlugin, Writer

from magnet import wire
from magnet.ros2 import messages, recording
from magnet.ros2.names import DEFAULT_NAMESPACE, validate_namespace
from services.common.endpoint import use_local_pipeline
from services.common.zenoh_session import add_zenoh_arguments, drain, open_session, payload_bytes, stop_event

log = logging.getLogger("magnet.record")

KINDS = (wire.Kind.RAW, wire.Kind.HEADING, wire.Kind.CALIBRATION, wire.Kind.ALERT)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="FILE.mcap (one file) or DIR (a rosbag2 directory)")
    parser.add_argument("--devices", default="*", help="key expression of the devices to record (default *, all)")
    parser.add_argument("--seconds", type=float, help="stop after this many seconds (default: at Ctrl-C)")
    parser.add_argument("--ros-namespace", default=DEFAULT_NAMESPACE, help="namespace of the topics (default /magnet)")
    add_zenoh_arguments(parser)


class _Bag:
    """A rosbag2 being written: one connection per topic, made when the topic first appears."""

    def __init__(self, path: Path) -> None:
        self.writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.connections: dict[str, Any] = {}
        self.written: Counter[str] = Counter()

    def write(self, rows: list[recording.Row]) -> None:
        for topic, ros_type, t_ns, data in rows:
            conn = self.connections.get(topic)
            if conn is None:
                conn = self.connections[topic] = self.writer.add_connection(topic, ros_type, typestore=messages.STORE)
            self.writer.write(conn, t_ns, data)
            self.written[ros_type] += 1


def _rows(kind: wire.Kind, payload: bytes, namespace: str) -> list[recording.Row]:
    """The recording rows of one message; ValueError (WireError) for one that does not decode."""
    if kind is wire.Kind.RAW:
        return recording.raw_rows(wire.decode_raw(payload, with_truth=False), namespace)
    if kind is wire.Kind.HEADING:
        return recording.heading_rows(wire.decode_heading(payload), namespace)
    now = time.time_ns()
    if kind is wire.Kind.CALIBRATION:
        return recording.calibration_rows(wire.decode_calibration(payload).to_record(), now, namespace)
    message = wire.unpack(payload)
    if not isinstance(message, dict) or not isinstance(message.get("device"), str):
        raise ValueError("an alert message must be a map with a device")
    return recording.alert_rows(message, now, namespace)


def _replies(asked: Any, limit: int) -> tuple[list[bytes], bool]:
    """The calibration replies ``asked`` holds now, and whether its query is finished (its channel closed)."""
    got: list[bytes] = []
    while len(got) < limit:
        try:
            reply = asked.try_recv()
        except zenoh.ZError:
            return got, True
        if reply is None:
            return got, False
        if reply.ok is not None:
            got.append(payload_bytes(reply.ok))
    return got, False


def _record(args: argparse.Namespace, bag: _Bag, stop: threading.Event) -> Counter[str]:
    dropped: Counter[str] = Counter()
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    with contextlib.ExitStack() as declared:
        session = declared.enter_context(open_session(args))
        subs = {
            k: declared.enter_context(session.declare_subscriber(f"{args.prefix}/{args.devices}/{k.value}"))
            for k in KINDS
        }
        asked: Any = session.get(f"{args.prefix}/{args.devices}/calibration", timeout=3.0)
        pending: list[tuple[wire.Kind, bytes]] = []
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            if asked is not None:  # the calibrations in force, written first as their replies come
                in_force, finished = _replies(asked, 10_000)
                pending += [(wire.Kind.CALIBRATION, payload) for payload in in_force]
                asked = None if finished else asked
            for kind, sub in subs.items():
                pending += [(kind, payload_bytes(s)) for s in drain(sub, 10_000)]
            for kind, payload in pending:
                try:
                    bag.write(_rows(kind, payload, args.ros_namespace))
                except ValueError as exc:
                    if not dropped[kind.value]:
                        log.warning(
                            "skipping %s messages that do not decode (%s); further ones only counted", kind, exc
                        )
                    dropped[kind.value] += 1
            if not pending:
                time.sleep(0.005)
            pending = []
    return dropped


def run(args: argparse.Namespace) -> int:
    use_local_pipeline(args)
    out: Path = args.out
    try:
        validate_namespace(args.ros_namespace)
        if args.seconds is not None and not args.seconds > 0:
            raise ValueError(f"--seconds must be > 0, got {args.seconds}")
        if out.exists():
            raise ValueError(f"{out} exists: give a new name")
    except ValueError as exc:
        print(f"magnet record: error: {exc}")
        return 2
    single = out.suffix.lower() == ".mcap"
    directory = out.with_name(out.name + ".bag") if single else out
    bag = _Bag(directory)
    try:
        dropped = _record(args, bag, stop_event())
    finally:
        bag.writer.close()
    if not bag.written:
        shutil.rmtree(directory, ignore_errors=True)
        heard = f", only {sum(dropped.values())} message(s) that did not decode" if dropped else ""
        print(
            f"magnet record: error: heard nothing on {args.prefix}/{args.devices}/...{heard}; no bag written (is a "
            "pipeline running, magnet up, or reachable with --connect?)",
            file=sys.stderr,
        )
        return 1
    if single:
        (directory / f"{directory.name}.mcap").rename(out)
        shutil.rmtree(directory)
    print(json.dumps({"out": str(out), "written": dict(bag.written), "dropped": dict(dropped)}), flush=True)
    return 0
