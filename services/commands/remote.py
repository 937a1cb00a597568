"""Remote tools: ``magnet get calibration DEVICE [--history]``, ``magnet get fleet``, ``magnet watch heading
[DEVICE]``, ``magnet calibrate DEVICE start|status|commit|abort [--method M]``, ``magnet calibrate DEVICE rollback
[--to ID]``. Tables on a terminal; JSON with ``--json`` or into a pipe (``remote_view``).

Given no ``--connect``, ``--listen`` or ``--config``, they reach the ``magnet up`` running for this user, if any
(``services.common.endpoint``). Exit status: 0 with an answer, 1 when nobody answered (no calibrator reachable, or
no calibration for the device).
"""

from __future__ import annotations

import argparse
import getpass
import logging
import socket
import sys
import time
from pathlib import Path
from typing import Any

from rich.console import Console

from magnet import signing, wire
from magnet.calibration.choose import parse_choice
from services.commands.remote_view import (
    calibrate_table,
    calibration_table,
    fleet_table,
    print_json,
    show,
    status_table,
    vehicle_table,
    wants_json,
    watch_line,
)
from services.common.endpoint import use_local_pipeline
from services.common.zenoh_session import add_zenoh_arguments, open_session, payload_bytes, stop_event

log = logging.getLogger("magnet.remote")

#: what `watch` can follow -> key kind
WATCHABLE = {
    "heading": wire.Kind.HEADING,
    "progress": wire.Kind.PROGRESS,
    "calibration": wire.Kind.CALIBRATION,
    "raw": wire.Kind.RAW,
    "alert": wire.Kind.ALERT,
}
ACTIONS = ("start", "status", "commit", "abort", "rollback")


def _print(value: Any) -> None:
    print_json(value)


def _add_json(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--json",
        action="store_true",
        help="print JSON, one object per line (the default when the output is not a terminal)",
    )


def _decode(payload: bytes) -> Any:
    """The message as printable JSON (v 2 binary arrays as lists)."""
    try:
        return wire.plain(wire.unpack(payload))
    except wire.WireError as exc:
        return {"error": str(exc)}


def ask(args: argparse.Namespace, selector: str, errors: list[str] | None = None) -> list[Any]:
    """Decoded answers (the ok replies) to ``selector``; error replies go to stderr (and to ``errors`` when given)."""
    with open_session(args) as session:
        out = []
        for reply in session.get(selector, timeout=args.timeout):
            if reply.ok is not None:
                out.append(_decode(payload_bytes(reply.ok)))
            elif reply.err is not None:
                message = payload_bytes(reply.err).decode(errors="replace")
                print(f"magnet: {message}", file=sys.stderr)
                if errors is not None:
                    errors.append(message)
        return out


# ----------------------------------------------------------------------------------------------------------- get


def add_get_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "what",
        choices=["calibration", "history", "status", "fleet", "vehicle"],
        help="a device's calibration, its history (calibration --history: every record, newest first, with what "
        "made each: a session, a rollback, an in-service refresh), a service's status counters, every device in one "
        "reply, or a vehicle's compasses compared (which one disagrees, why, the parameter that fixes it: "
        "docs/vehicles.md)",
    )
    parser.add_argument(
        "device",
        nargs="?",
        help="device id (or '*'); for status: the service name (calibrator, compass, '*'); for vehicle: the vehicle "
        "(MAVLink: mav<SYSID>, or '*')",
    )
    parser.add_argument("--history", action="store_true", help="earlier calibrations too, newest first")
    parser.add_argument("--limit", type=int, default=20, help="with --history: at most this many (default 20)")
    parser.add_argument("--timeout", type=float, default=3.0, help="seconds to wait for answers (default 3)")
    parser.add_argument(
        "--trust",
        action="append",
        default=[],
        type=Path,
        metavar="FILE.pub",
        help="print only calibrations signed by this public key (repeatable); others are named on stderr",
    )
    _add_json(parser)
    add_zenoh_arguments(parser)


def _trusted_record(record: Any, trusted: signing.TrustedKeys) -> str | None:
    """None when ``record`` is a calibration signed by a trusted key, else why not."""
    try:
        trusted.verify(wire.calibration_from_record(record).to_record())
    except (wire.WireError, signing.SignatureError) as exc:
        return str(exc)
    return None


def _only_trusted(answers: list[Any], trusted: signing.TrustedKeys, device: str) -> list[Any]:
    """The answers (records, or history maps of records) with every untrusted record left out and named."""
    out = []
    for answer in answers:
        records = answer.get("records") if isinstance(answer, dict) and "records" in answer else [answer]
        kept = []
        for record in records if isinstance(records, list) else []:
            reason = _trusted_record(record, trusted)
            if reason is None:
                kept.append(record)
            else:
                name = record.get("device", device) if isinstance(record, dict) else device
                print(f"magnet get: refusing a calibration of {name}: {reason}", file=sys.stderr)
        if isinstance(answer, dict) and "records" in answer:
            out.append({**answer, "records": kept})
        else:
            out += kept
    return out


def run_get(args: argparse.Namespace) -> int:
    use_local_pipeline(args)
    if args.what == "fleet":
        replies = ask(args, f"{args.prefix}/@fleet")
        for reply in replies[:1]:
            show(args, reply, fleet_table)
        if not replies:
            print("magnet get: no calibrator answered for the fleet", file=sys.stderr)
        return 0 if replies else 1
    if args.device is None:
        raise ValueError(f"magnet get {args.what} needs a device id (or '*')")
    if args.device != "*":
        wire.validate_device_id(args.device)
    if args.what == "vehicle":
        return _get_vehicle(args)
    if args.what == "status":
        replies = ask(args, wire.status_key(args.prefix, args.device))
        for reply in replies:
            show(args, reply, status_table)
        if not replies:
            print(
                f"magnet get: no service named {args.device!r} answered for its status (the names are 'calibrator', "
                "'compass', 'edge-...' or '*' for every one; is the pipeline running and reachable?)",
                file=sys.stderr,
            )
        return 0 if replies else 1
    history = args.history or args.what == "history"
    kind = wire.Kind.HISTORY if history else wire.Kind.CALIBRATION
    selector = f"{args.prefix}/{args.device}/{kind.value}" + (f"?limit={args.limit}" if history else "")
    trusted = signing.TrustedKeys([signing.load_public_key(path.read_bytes(), str(path)) for path in args.trust])
    replies = ask(args, selector)
    if trusted.enabled:
        replies = _only_trusted(replies, trusted, args.device)
    if history:  # a calibrator says a device it serves has none stored (it used to stay silent)
        replies = [r for r in replies if not (isinstance(r, dict) and not r.get("records"))]
    if not replies:
        print(
            f"magnet get: no {'trusted ' if trusted.enabled else ''}calibration for {args.device} (is a "
            "calibrator running and reachable?)",
            file=sys.stderr,
        )
        return 1
    for reply in replies:
        show(args, reply, calibration_table)
    return 0


def _get_vehicle(args: argparse.Namespace) -> int:
    replies = ask(args, wire.vehicle_key(args.prefix, args.device))
    for reply in replies:
        show(args, reply, vehicle_table)
    if not replies:
        print(
            f"magnet get: no compass knows vehicle {args.device!r} (its compasses are named <vehicle>-mag<N>, as "
            "magnet edge --mavlink names them; is a compass running, reachable and fed by the vehicle?)",
            file=sys.stderr,
        )
    return 0 if replies else 1


# --------------------------------------------------------------------------------------------------------- watch


def add_watch_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", choices=list(WATCHABLE), help="what to follow")
    parser.add_argument("device", nargs="?", default="*", help="device id (default: every device)")
    parser.add_argument("--count", type=int, help="stop after this many messages")
    parser.add_argument("--duration", type=float, help="stop after this many seconds")
    _add_json(parser)
    add_zenoh_arguments(parser)


def run_watch(args: argparse.Namespace) -> int:
    use_local_pipeline(args)
    if args.device != "*":
        wire.validate_device_id(args.device)
    stop = stop_event()
    deadline = None if args.duration is None else time.monotonic() + args.duration
    printed = 0
    console = None if wants_json(args) else Console()
    key = f"{args.prefix}/{args.device}/{WATCHABLE[args.what].value}"
    with open_session(args) as session, session.declare_subscriber(key) as subscriber:
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            sample = subscriber.try_recv()
            if sample is None:
                time.sleep(0.002)
                continue
            message = {"key": str(sample.key_expr), **_shown(args.what, _as_map(_decode(payload_bytes(sample))))}
            if console is None:
                _print(message)
            else:
                console.print(watch_line(message))
            printed += 1
            if args.count is not None and printed >= args.count:
                break
    if printed == 0 and not stop.is_set():
        # no heading in the time given is an error (nobody publishes); no alert is good news, said all the same
        trouble = args.what == "heading"
        print(
            f"magnet watch: heard no {args.what} on {key}"
            + (" (is a compass running and reachable?)" if trouble else " (none raised)"),
            file=sys.stderr,
        )
        return 1 if trouble else 0
    return 0


def _as_map(value: Any) -> dict[str, Any]:
    return value if isinstance(value, dict) else {"value": value}


def _shown(what: str, message: dict[str, Any]) -> dict[str, Any]:
    """``message`` as printed: an alert with the advice of the fixed table (``magnet.drift.advice_for``), never
    the sender's words; a malformed alert as it came."""
    if what != "alert":
        return message
    from magnet.drift import alert_from_message

    try:
        return {**message, "advice": alert_from_message(message).advice}
    except ValueError:
        return message


# ----------------------------------------------------------------------------------------------------- calibrate


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("device", help="device id")
    parser.add_argument("action", choices=ACTIONS, help="what to do with the device's calibration session")
    parser.add_argument("--method", help="fit method for 'start' (default: the calibrator's)")
    parser.add_argument(
        "--to",
        metavar="ID",
        help="for 'rollback': the calibration id to put back in force "
        "(default: the one before the calibration in force)",
    )
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the answer (default 5)")
    _add_json(parser)
    add_zenoh_arguments(parser)


def run_calibrate(args: argparse.Namespace) -> int:
    use_local_pipeline(args)
    wire.validate_device_id(args.device)
    if args.method:
        parse_choice(args.method)  # a method no calibrator knows: one line here, exit 2
    params = f"action={args.action}" + (f";method={args.method}" if args.method else "")
    if args.action == "rollback":
        params += (f";to={args.to}" if args.to else "") + f";by={_who()}"
    elif args.to:
        raise ValueError("--to goes with rollback")
    elif args.action in ("start", "commit"):
        params += f";by={_who()}"  # recorded with the commit
    errors: list[str] = []
    replies = ask(args, f"{args.prefix}/{args.device}/{wire.Kind.CALIBRATE.value}?{params}", errors)
    if not replies:
        if not errors:
            print(f"magnet calibrate: no calibrator answered for {args.device}", file=sys.stderr)
        return 1
    for reply in replies:
        show(args, reply, calibrate_table)
        if isinstance(reply, dict) and not reply.get("ok", False):
            print(f"magnet calibrate: refused: {reply.get('message', '')}", file=sys.stderr)
    return 0 if all(isinstance(r, dict) and r.get("ok", False) for r in replies) else 1


def _who() -> str:
    """user@host of the person asking (recorded with a commit or a rollback); characters that a selector cannot
    carry dropped."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "unknown"
    text = f"{user}@{socket.gethostname()}"
    return "".join(c for c in text if c.isalnum() or c in "@.-_")[:128]


# services.cli looks up ``add_arguments``/``run`` as a fallback even where ``add_<name>_arguments`` exists
add_arguments, run = add_get_arguments, run_get
