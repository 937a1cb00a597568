"""The calibrator's queryables: the record in force, its history, operator sessions and the fleet.
A calibrator started with ``--shard K/N`` answers only for its own devices (the others' shards answer for theirs).

``<prefix>/<dev>/calibration`` (record in force), ``<prefix>/<dev>/calibration/history?limit=N`` (``{v, device,
records: [...]}`` newest first), ``<prefix>/<dev>/calibrate?action=...&method=...``, ``<prefix>/@fleet``; the status,
``<prefix>/@status/<name>``, is answered from Zenoh's thread (``services.common.status_board``). Each handler answers
one query (``reply`` or ``reply_err``); none raises on what a peer sends. A calibrator standing by (another of its
shard holds the lease, ``services.calibrator.lease``) answers only its status.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import zenoh

from magnet import wire
from magnet.calibrator.core import CalibratorCore
from magnet.calibrator.roster_reply import roster_reply

#: history replies hold at most this many records
MAX_HISTORY_LIMIT = 10_000
DEFAULT_HISTORY_LIMIT = 100


def matching_devices(devices: Iterable[str], prefix: str, key_expr: str, kind: wire.Kind) -> list[str]:
    """The devices of ``devices`` whose ``<prefix>/<device>/<kind>`` key the queried ``key_expr`` names."""
    if not any(c in key_expr for c in "*$"):
        try:
            device = wire.device_from_key(prefix, key_expr, kind)
        except wire.WireError:
            return []
        return [device] if device in devices else []
    asked = zenoh.KeyExpr(key_expr)
    return [d for d in devices if asked.intersects(zenoh.KeyExpr(wire.key(prefix, d, kind)))]


#: how a query is answered: (query, calibrator, prefix)
Answer = Callable[[zenoh.Query, CalibratorCore, str], None]


def active_only(answer: Answer) -> Answer:
    """``answer``, given only while the calibrator holds the lease of its shard (else the query goes unanswered)."""

    def when_active(query: zenoh.Query, calibrator: CalibratorCore, prefix: str) -> None:
        if calibrator.active:
            answer(query, calibrator, prefix)

    return when_active


def answer_calibration(query: zenoh.Query, calibrator: CalibratorCore, prefix: str) -> None:
    in_force = calibrator.records.in_force
    for device in matching_devices(in_force, prefix, str(query.key_expr), wire.Kind.CALIBRATION):
        query.reply(wire.key(prefix, device, wire.Kind.CALIBRATION), wire.pack(in_force[device].to_record()))


def history_limit(text: str | None) -> int:
    """The ``limit`` parameter (default 100), clamped to 0..MAX_HISTORY_LIMIT; ValueError when not a whole number."""
    if not text:
        return DEFAULT_HISTORY_LIMIT
    try:
        limit = int(text)
    except ValueError:
        raise ValueError("limit must be a whole number") from None
    return min(max(0, limit), MAX_HISTORY_LIMIT)


def answer_history(query: zenoh.Query, calibrator: CalibratorCore, prefix: str) -> None:
    try:
        limit = history_limit(query.parameters.get("limit"))
    except ValueError as exc:
        query.reply_err(str(exc).encode())
        return
    key_expr = str(query.key_expr)
    devices = matching_devices(calibrator.records.in_force, prefix, key_expr, wire.Kind.HISTORY)
    named = named_device(prefix, key_expr, wire.Kind.HISTORY)
    if named is not None and not devices and calibrator.shard.owns(named):
        devices = [named]  # one device of this shard asked by name: its history, or that it has none (not silence)
    for device in devices:
        try:
            rows = calibrator.records.store.history_changes(device, limit=limit)
        except OSError as exc:  # a damaged page: say so, keep serving
            query.reply_err(str(exc).encode())
            return
        records = [record.to_record() for record, _ in rows]  # as stored: signed when made, or not at all
        answer = {"device": device, "records": records, "changes": [change for _, change in rows]}
        if not records:
            answer["message"] = f"no calibration is stored for {device}"
        query.reply(wire.key(prefix, device, wire.Kind.HISTORY), wire.pack(answer))


def named_device(prefix: str, key_expr: str, kind: wire.Kind) -> str | None:
    """The one device a key names (no wildcard) when it is a valid ``<prefix>/<device>/<kind>`` key, else None."""
    if any(c in key_expr for c in "*$"):
        return None
    try:
        return wire.device_from_key(prefix, key_expr, kind)
    except wire.WireError:
        return None


def answer_calibrate(query: zenoh.Query, calibrator: CalibratorCore, prefix: str) -> None:
    key_expr = str(query.key_expr)
    try:
        device = wire.device_from_key(prefix, key_expr, wire.Kind.CALIBRATE)
        if not calibrator.shard.owns(device):
            return  # another shard's device: that shard answers
        action = query.parameters.get("action") or "status"
        if action == "rollback":
            reply = calibrator.rollback(device, query.parameters.get("to"), query.parameters.get("by"))
        else:
            reply = calibrator.session(device, action, query.parameters.get("method"), query.parameters.get("by"))
    except ValueError as exc:
        query.reply_err(str(exc).encode())
        return
    query.reply(key_expr, wire.pack(reply))


def answer_fleet(query: zenoh.Query, calibrator: CalibratorCore, prefix: str) -> None:
    """``<prefix>/@fleet``: every device in one reply (``magnet.calibrator.roster_reply``)."""
    reply = roster_reply(
        calibrator.records.in_force, calibrator.collections, calibrator.roster, calibrator.state, calibrator.clock_ns()
    )
    query.reply(f"{prefix}/@fleet", wire.pack(reply))


#: queried kind -> how to answer (the status is answered from Zenoh's thread: ``services.common.status_board``)
ANSWERS: dict[wire.Kind, Answer] = {
    wire.Kind.CALIBRATION: active_only(answer_calibration),
    wire.Kind.HISTORY: active_only(answer_history),
    wire.Kind.CALIBRATE: active_only(answer_calibrate),
}
#: the ``<prefix>/@fleet`` handler of the service
FLEET_ANSWER = active_only(answer_fleet)


def board_status(calibrator: CalibratorCore, name: str) -> dict[str, Any]:
    """What the loop writes on its status board (from the loop's thread): the status and the alerts open by kind;
    the status queryable and ``--metrics`` both read it from there."""
    alerts: dict[str, int] = {}
    for open_alerts in calibrator.roster.alerts.values():
        for kind in open_alerts:
            alerts[kind.value] = alerts.get(kind.value, 0) + 1
    return {**calibrator.status(name).to_dict(), "alerts_open": alerts}
