"""How the remote tools print: JSON for scripts, tables for people.

``--json``, or an output that is not a terminal (a pipe, a file, a script's capture), gives exactly the JSON the
tools always printed: one object per line, keys sorted. On a terminal without ``--json`` the answers are ``rich``
tables with units and sensible precision: angles to 0.1 deg, fields to 0.01 uT, coverage in %, ages in s / min / h /
d. The rendering functions return ``rich`` renderables and take no terminal: tests render them to text.
"""

from __future__ import annotations

import datetime
import json
import sys
from collections.abc import Mapping
from typing import Any

from rich.console import Console, Group, RenderableType
from rich.table import Table
from rich.text import Text

DRIFT_UNITS = {"field_strength": "uT", "dip": "deg", "calibration_age": "days"}


def wants_json(args: Any) -> bool:
    """JSON with ``--json`` or when stdout is no terminal (scripts keep today's output)."""
    return bool(getattr(args, "json", False)) or not sys.stdout.isatty()


def print_json(value: Any) -> None:
    print(json.dumps(value, sort_keys=True), flush=True)


def show(args: Any, value: Any, render: Any) -> None:
    """Print ``value`` as JSON (``wants_json``) or as ``render(value)`` on the terminal."""
    if wants_json(args):
        print_json(value)
    else:
        Console().print(render(value))


# ------------------------------------------------------------------------------------------------------- figures
def num(value: Any, digits: int, unit: str = "") -> str:
    """A number to ``digits`` decimals with its unit; an en dash when missing."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "\u2013"
    return f"{value:.{digits}f}" + (f" {unit}" if unit else "")


def unit_name(unit: Any) -> str:
    """A record's unit as people write it (uT for ``ut``)."""
    return {"ut": "uT", None: "uT", "nt": "nT", "mgauss": "mG"}.get(unit, str(unit))


def pct(value: Any) -> str:
    return "\u2013" if not isinstance(value, (int, float)) or isinstance(value, bool) else f"{value * 100:.0f} %"


def age(seconds: Any) -> str:
    if not isinstance(seconds, (int, float)) or isinstance(seconds, bool):
        return "\u2013"
    for limit, div, unit in ((90, 1, "s"), (5400, 60, "min"), (172800, 3600, "h")):
        if seconds < limit:
            return f"{seconds / div:.0f} {unit}" if unit != "h" else f"{seconds / div:.1f} h"
    return f"{seconds / 86400:.0f} d"


def when(t_ns: Any) -> str:
    """A wall-clock time (ns since the epoch) in local time to the second."""
    if not isinstance(t_ns, int) or isinstance(t_ns, bool):
        return "\u2013"
    return datetime.datetime.fromtimestamp(t_ns / 1e9).strftime("%Y-%m-%d %H:%M:%S")


def alert_text(alert: Mapping[str, Any]) -> str:
    unit = DRIFT_UNITS.get(str(alert.get("kind")), "")
    return (
        f"{str(alert.get('kind', '?')).replace('_', ' ')}: {num(alert.get('measured'), 1, unit)} "
        f"(expected {num(alert.get('expected'), 1, unit)}) - {alert.get('advice', '')}"
    )


# -------------------------------------------------------------------------------------------------------- tables
def fleet_table(answer: Mapping[str, Any]) -> RenderableType:
    """``magnet get fleet``: one row per device, its open alerts with their advice under the table."""
    devices = answer.get("devices") or []
    table = Table(title=f"{answer.get('count', len(devices))} device(s)", title_justify="left")
    for name, justify in (
        ("device", "left"),
        ("state", "left"),
        ("method", "left"),
        ("residual uT", "right"),
        ("coverage", "right"),
        ("age", "right"),
        ("place (lat, lon)", "left"),
        ("alerts", "left"),
    ):
        table.add_column(name, justify=justify)  # type: ignore[arg-type]
    notes = []
    for entry in devices:
        quality = entry.get("quality") or {}
        alerts = entry.get("alerts") or []
        place = entry.get("location")
        where = "\u2013" if not place else f"{place[0]:.2f}, {place[1]:.2f} ({entry.get('location_source')})"
        state = str(entry.get("state"))
        table.add_row(
            str(entry.get("device")),
            Text(state + (" (drift alert)" if alerts else ""), style="red" if alerts else ""),
            str(entry.get("method") or "\u2013"),
            num(quality.get("residual_rms_ut"), 2),
            pct(quality.get("coverage")),
            age(entry.get("age_s")),
            where,
            Text(", ".join(str(a.get("kind")) for a in alerts) or "ok", style="red" if alerts else "green"),
        )
        notes += [Text(f"{entry.get('device')}: {alert_text(a)}", style="red") for a in alerts]
    return Group(table, *notes)


def calibration_table(record: Mapping[str, Any]) -> RenderableType:
    """``magnet get calibration DEVICE``: the record in force, offset and matrix included."""
    if "records" in record:
        return history_table(record)
    quality = record.get("quality") or {}
    table = Table(show_header=False, title=f"calibration of {record.get('device')}", title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    offset = record.get("offset") or []
    matrix = record.get("matrix") or []
    rows = [
        ("id", str(record.get("id"))),
        ("created", when(record.get("created_ns"))),
        ("method", str(record.get("method"))),
        ("accepted", f"{record.get('accepted')} {record.get('reason') or ''}".strip()),
        ("offset", " ".join(f"{num(x, 2):>8}" for x in offset) + f" {unit_name(record.get('unit'))}"),
        ("matrix", "\n".join(" ".join(f"{num(x, 4):>8}" for x in row) for row in matrix)),
        ("field strength", num(record.get("field_strength"), 2, unit_name(record.get("output_unit")))),
        ("residual", num(quality.get("residual_rms_ut"), 2, "uT")),
        ("held-out residual", num(quality.get("holdout_rms_ut"), 2, "uT")),
        ("coverage", pct(quality.get("coverage"))),
        ("signed by", str(record.get("key_id") or "\u2013")),
    ]
    if isinstance(record.get("hardware_id"), int):  # the sensor it was fitted for (docs/mavlink.md)
        rows.insert(3, ("sensor", _sensor(record["hardware_id"])))
    for name, value in rows:
        table.add_row(name, value)
    return table


def _sensor(hardware_id: int) -> str:
    """A record's hardware id, decoded as the autopilots pack it when it fits their 24 bits."""
    from magnet.autopilot.hwid import MAX_HARDWARE_ID, describe

    return describe(hardware_id) if 0 < hardware_id <= MAX_HARDWARE_ID else str(hardware_id)


def history_table(answer: Mapping[str, Any]) -> RenderableType:
    """``magnet get calibration DEVICE --history``: newest first, and the changes (rollbacks) with who made them."""
    table = Table(title=f"history of {answer.get('device')}", title_justify="left")
    for name in ("created", "id", "method", "residual uT", "coverage", "gate"):
        table.add_column(name, justify="right" if name in ("residual uT", "coverage") else "left")
    for record in answer.get("records") or []:
        quality = record.get("quality") or {}
        table.add_row(
            when(record.get("created_ns")),
            str(record.get("id")),
            str(record.get("method")),
            num(quality.get("residual_rms_ut"), 2),
            pct(quality.get("coverage")),
            "accepted" if record.get("accepted") else "rejected",
        )
    changes = [
        Text(
            f"{when(c.get('at_ns'))} {c.get('action')}{_in_service(c)} from {c.get('from_id')} by {c.get('by') or '?'}"
        )
        for c in answer.get("changes") or []
    ]
    return Group(table, *changes)


def _in_service(change: Mapping[str, Any]) -> str:
    """ " (made in service, ...)" for a record an in-service refresh made (``magnet.calibrator.refresh``), else ""."""
    if not change.get("in_service"):
        return ""
    gain = change.get("gain_pct")
    parts = ["made in service"] + ([f"{gain:.0f} % more consistent"] if isinstance(gain, (int, float)) else [])
    resolves = change.get("resolves") or []
    if resolves:
        parts.append(f"resolves drift alert {', '.join(str(a) for a in resolves)}")
    return f" ({'; '.join(parts)})"


def status_table(answer: Mapping[str, Any]) -> RenderableType:
    """``magnet get status``: a service's counters, one per line."""
    table = Table(show_header=False, title=str(answer.get("name", "status")), title_justify="left")
    table.add_column(style="bold")
    table.add_column(justify="right")
    for key, value in sorted(answer.items()):
        table.add_row(key, num(value, 3) if isinstance(value, float) else json.dumps(value, sort_keys=True))
    return table


def calibrate_table(answer: Mapping[str, Any]) -> RenderableType:
    """``magnet calibrate``: the answer, the session's progress and any calibration it put in force."""
    ok = bool(answer.get("ok"))
    lines: list[RenderableType] = [Text(str(answer.get("message", "")), style="green" if ok else "red")]
    progress = answer.get("progress") or {}
    if progress:
        table = Table(show_header=False, title="session", title_justify="left")
        table.add_column(style="bold")
        table.add_column()
        for name, value in (
            ("state", progress.get("state")),
            ("method", progress.get("method")),
            ("samples", progress.get("samples")),
            ("coverage", pct(progress.get("coverage"))),
            ("residual", num(progress.get("residual_rms_ut"), 2, "uT")),
            ("gate", "passes" if progress.get("accepted") else "not yet"),
            ("next", "; ".join(progress.get("missing") or ()) or progress.get("reason") or ""),
        ):
            table.add_row(name, "\u2013" if value is None else str(value))
        lines.append(table)
    if isinstance(answer.get("calibration"), Mapping):
        lines.append(calibration_table(answer["calibration"]))
    return Group(*lines)


def watch_line(message: Mapping[str, Any]) -> RenderableType:
    """``magnet watch``: one line per message; a heading message by its last sample."""
    device, key = message.get("device", "?"), str(message.get("key", ""))
    if isinstance(message.get("true_heading_deg"), list) and message["true_heading_deg"]:
        last = {name: (message.get(name) or [None])[-1] for name in ("true_heading_deg", "heading_deg")}
        pitch, roll = (message.get("pitch_deg") or [None])[-1], (message.get("roll_deg") or [None])[-1]
        field = (message.get("field_ut") or [None])[-1]
        strength = None if not field else sum(x * x for x in field) ** 0.5
        return Text(
            f"{device}  seq {message.get('seq')}  true {num(last['true_heading_deg'], 1, 'deg')}  "
            f"magnetic {num(last['heading_deg'], 1, 'deg')}  pitch {num(pitch, 1, 'deg')}  "
            f"roll {num(roll, 1, 'deg')}  |B| {num(strength, 1, 'uT')}"
        )
    if "kind" in message and "advice" in message:
        cleared = " cleared" if message.get("cleared") else ""
        return Text(f"{device}  ALERT{cleared} {alert_text(message)}", style="" if cleared else "red")
    if "state" in message:
        return Text(
            f"{device}  {message.get('state')}  coverage {pct(message.get('coverage'))}  "
            f"{message.get('samples', '')} samples  {'; '.join(message.get('missing') or ())}"
        )
    return Text(f"{key}  {json.dumps({k: v for k, v in message.items() if k != 'key'}, sort_keys=True)[:200]}")


def vehicle_table(answer: Mapping[str, Any]) -> RenderableType:
    """``magnet get vehicle``: one row per compass (verdict, angle to the reference, rotation, interference,
    residual, the parameters to set) and the summary under it."""
    table = Table(title=f"vehicle {answer.get('vehicle')}", title_justify="left")
    for name in ("compass", "verdict", "angle", "rotation", "interference", "residual", "set"):
        table.add_column(name)
    for c in answer.get("compasses") or []:
        named = c.get("named_rotation")
        params = c.get("parameters") or {}
        table.add_row(
            str(c.get("device")),
            Text(str(c.get("verdict")), style=_VERDICT_STYLES.get(str(c.get("verdict")), "")),
            num(c.get("angle_deg"), 1, "deg"),
            f"{num(c.get('rotation_deg'), 0, 'deg')}" + (f" (named {named})" if named is not None else ""),
            num(c.get("interference_pct"), 0, "%"),
            num(c.get("residual_ut"), 1, "uT"),
            ", ".join(f"{k}={v:g}" for k, v in params.items()) or "\u2013",
        )
    return Group(table, Text(str(answer.get("summary", ""))))


_VERDICT_STYLES = {"agrees": "green", "reference": "green", "rotation": "red", "interference": "red"}
