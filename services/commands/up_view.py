"""The live view of ``magnet up``: what is known of each device, fed from the messages, printed as text.

On a terminal the view is redrawn in place with ``rich``'s ``Live`` (no clearing of the screen, so no flicker);
elsewhere (CI, pipes) it prints plain blocks of lines. Open drift alerts are counted in the first line, mark the
device's state and are listed under the table with their cause and advice, wrapped at word boundaries.
"""

from __future__ import annotations

import dataclasses
import textwrap
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from magnet import wire
from magnet.drift import Alert, alert_from_message

if TYPE_CHECKING:
    from rich.live import Live

NOTE_CHARS = 76
DRIFT_UNITS = {"field_strength": "uT", "dip": "deg", "calibration_age": "days"}


@dataclasses.dataclass
class DeviceView:
    """What the view knows of one device."""

    state: str = "waiting"
    coverage: float | None = None
    samples: int | None = None
    missing: tuple[str, ...] = ()
    reason: str = ""
    residual_ut: float | None = None
    calibration_id: str = ""
    true_heading_deg: float | None = None
    pitch_deg: float | None = None
    roll_deg: float | None = None
    flags: int = 0
    truth: dict[int, float] = dataclasses.field(default_factory=dict)  # seq -> true heading of the last sample
    error_deg: float | None = None
    alerts: dict[str, Alert] = dataclasses.field(default_factory=dict)  # open drift alerts by kind

    @property
    def status(self) -> str:
        """The state column: a calibrated device with an open drift alert reads "drifted"."""
        return "drifted" if self.alerts and self.state == "calibrated" else self.state

    def on_alert(self, alert: Alert) -> None:
        if alert.cleared:
            self.alerts.pop(alert.kind.value, None)
        else:
            self.alerts[alert.kind.value] = alert

    def on_progress(self, message: dict[str, Any]) -> None:
        self.state = str(message.get("state", self.state))
        self.coverage = message.get("coverage", self.coverage)
        self.samples = message.get("samples", self.samples)
        self.missing = tuple(message.get("missing") or ())
        self.reason = str(message.get("reason") or "")
        self.residual_ut = message.get("residual_rms_ut", self.residual_ut)
        self.calibration_id = message.get("calibration_id") or self.calibration_id

    def on_calibration(self, message: dict[str, Any]) -> None:
        self.state = "calibrated"
        self.calibration_id = str(message.get("id", ""))
        self.residual_ut = (message.get("quality") or {}).get("residual_rms_ut", self.residual_ut)
        self.coverage = (message.get("quality") or {}).get("coverage", self.coverage)

    def on_raw(self, batch: wire.RawBatch) -> None:
        if batch.truth is not None:
            self.truth[batch.seq] = float(batch.truth["heading_deg"][-1])
            if len(self.truth) > 64:
                self.truth.pop(next(iter(self.truth)))

    def on_heading(self, batch: wire.HeadingBatch) -> None:
        if batch.calibration_id and self.state == "waiting":  # the compass applies a calibration: one is in force
            self.state, self.calibration_id = "calibrated", batch.calibration_id
        self.true_heading_deg = float(batch.true_heading_deg[-1])
        self.pitch_deg, self.roll_deg = float(batch.pitch_deg[-1]), float(batch.roll_deg[-1])
        self.flags = int(batch.flags[-1])
        truth = self.truth.get(batch.seq)
        if truth is not None:
            self.error_deg = float((self.true_heading_deg - truth + 180.0) % 360.0 - 180.0)


def _bar(fraction: float | None, width: int = 20, state: str = "waiting") -> str:
    if fraction is None:
        return "waiting for samples" if state == "waiting" else "-"
    filled = round(max(0.0, min(1.0, fraction)) * width)
    return "[" + "#" * filled + "." * (width - filled) + f"] {fraction:4.0%}"


def _fmt(value: float | None, spec: str) -> str:
    """``value`` in ``spec`` ("8.1f"), or "-" in the same width when there is none."""
    return "-".rjust(int(spec.split(".")[0])) if value is None or not np.isfinite(value) else format(value, spec)


def alert_cause(alert: Alert) -> str:
    """What departed, with the measured and expected figures and their unit."""
    unit = DRIFT_UNITS.get(alert.kind.value, "")
    return f"{alert.kind.value.replace('_', ' ')} {alert.measured:.1f} {unit} (expected {alert.expected:.1f} {unit})"


def _note(v: DeviceView) -> str:
    if v.alerts:
        note = "ALERT " + "; ".join(alert_cause(a) for _, a in sorted(v.alerts.items()))
    elif v.state == "calibrated":
        note = f"calibration {v.calibration_id}"
    else:
        note = ", ".join(v.missing) or v.reason
    return textwrap.shorten(note, NOTE_CHARS, placeholder=" ...") if note else ""


#: what the columns mean, under the table
LEGEND = (
    "hdg: true heading (from true north: the WMM's declination added), deg; err: hdg minus the simulator's true "
    "heading, deg; resid: the calibration's residual, uT"
)


def render_lines(views: dict[str, DeviceView], elapsed_s: float, width: int = 80) -> list[str]:
    """The view as lines of text (no terminal codes) that fit 80 columns: a header, one row per device with its note
    on the line below, each open alert's advice wrapped to ``width`` at word boundaries, and the legend."""
    calibrated = sum(v.state == "calibrated" for v in views.values())
    alerts = sum(len(v.alerts) for v in views.values())
    head = f"magnet up: {len(views)} device(s), {calibrated} calibrated, {alerts} alert(s), {elapsed_s:5.1f} s"
    lines = [
        head + "   (Ctrl-C stops)",
        f"{'device':<11} {'state':<10} {'coverage':<19} {'hdg':>8} {'pitch':>6} {'roll':>6} {'resid':>6} {'err':>6}",
    ]
    for device in sorted(views):
        v = views[device]
        lines.append(
            f"{device:<11} {v.status:<10} {_bar(v.coverage, width=12, state=v.state):<19} "
            f"{_fmt(v.true_heading_deg, '8.1f')} {_fmt(v.pitch_deg, '6.1f')} {_fmt(v.roll_deg, '6.1f')} "
            f"{_fmt(v.residual_ut, '6.2f')} {_fmt(v.error_deg, '6.2f')}"
        )
        note = _note(v)
        if note:
            lines.append(f"  {note}")
    for device in sorted(d for d in views if views[d].alerts):
        for _, alert in sorted(views[device].alerts.items()):
            text = f"ALERT {device}: {alert_cause(alert)}: {alert.advice}"
            lines += textwrap.wrap(text, width, subsequent_indent="    ")
    return [*lines, *textwrap.wrap(LEGEND, width)]


class Viewer:
    """Feeds DeviceViews from the messages and prints them (redrawn on a terminal, plain lines otherwise)."""

    def __init__(self, prefix: str, out: TextIO, tty: bool) -> None:
        self.prefix, self.out, self.tty = prefix, out, tty
        self.views: dict[str, DeviceView] = {}
        self.live: Live | None = None

    def view(self, device: str) -> DeviceView:
        return self.views.setdefault(device, DeviceView())

    def feed(self, kind: wire.Kind, payload: bytes) -> None:
        try:
            if kind is wire.Kind.RAW:
                batch = wire.decode_raw(payload)
                self.view(batch.device).on_raw(batch)
            elif kind is wire.Kind.HEADING:
                heading = wire.decode_heading(payload)
                self.view(heading.device).on_heading(heading)
            elif kind is wire.Kind.ALERT:
                message = wire.unpack(payload)
                alert = alert_from_message(message)
                self.view(wire.message_device(message)).on_alert(alert)
            elif kind is wire.Kind.PROGRESS:
                message = wire.decode_progress(payload)
                self.view(message["device"]).on_progress(message)
            else:
                message = wire.unpack(payload, wire.CALIBRATION_LIMITS)
                self.view(str(message.get("device"))).on_calibration(message)
        except (wire.WireError, KeyError, TypeError, ValueError):
            pass  # the services count malformed input; the view just skips it

    def show(self, elapsed_s: float) -> None:
        if not self.tty:
            self.out.write("\n".join(render_lines(self.views, elapsed_s)) + "\n\n")
            self.out.flush()
            return
        from rich.console import Console
        from rich.live import Live
        from rich.text import Text

        if self.live is None:
            console = Console(file=self.out)
            self.live = Live(console=console, auto_refresh=False, vertical_overflow="visible")
            self.live.start()
        width = max(60, min(80, self.live.console.width - 1))
        text = Text()
        for line in render_lines(self.views, elapsed_s, width):
            style = "bold red" if line.startswith("ALERT") or " drifted " in line else None
            text.append(line, style=style)
            text.append("\n")
        self.live.update(text, refresh=True)

    def close(self) -> None:
        """Leave the last view on the terminal."""
        if self.live is not None:
            self.live.stop()
            self.live = None
