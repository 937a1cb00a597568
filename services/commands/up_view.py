"""The live view of ``magnet up``: what is known of each device, fed from the messages, printed as text."""

from __future__ import annotations

import dataclasses
from typing import Any, TextIO

import numpy as np

from magnet import wire


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
        self.true_heading_deg = float(batch.true_heading_deg[-1])
        self.pitch_deg, self.roll_deg = float(batch.pitch_deg[-1]), float(batch.roll_deg[-1])
        self.flags = int(batch.flags[-1])
        truth = self.truth.get(batch.seq)
        if truth is not None:
            self.error_deg = float((self.true_heading_deg - truth + 180.0) % 360.0 - 180.0)


def _bar(fraction: float | None, width: int = 20) -> str:
    if fraction is None:
        return "[" + "?" * width + "]"
    filled = round(max(0.0, min(1.0, fraction)) * width)
    return "[" + "#" * filled + "." * (width - filled) + f"] {fraction:4.0%}"


def _fmt(value: float | None, spec: str) -> str:
    return "-" if value is None or not np.isfinite(value) else format(value, spec)


def render_lines(views: dict[str, DeviceView], elapsed_s: float) -> list[str]:
    """The view as lines of text (no terminal codes)."""
    calibrated = sum(v.state == "calibrated" for v in views.values())
    lines = [
        f"magnet up: {len(views)} device(s), {calibrated} calibrated, {elapsed_s:5.1f} s   (Ctrl-C stops)",
        (
            f"{'device':<12} {'state':<11} {'coverage':<31} {'heading':>8} {'pitch':>6} {'roll':>7} "
            f"{'resid uT':>8} {'err deg':>7}  note"
        ),
    ]
    for device in sorted(views):
        v = views[device]
        note = ", ".join(v.missing) if v.state != "calibrated" else f"calibration {v.calibration_id}"
        if v.state != "calibrated" and v.reason and not v.missing:
            note = v.reason
        lines.append(
            f"{device:<12} {v.state:<11} {_bar(v.coverage):<31} {_fmt(v.true_heading_deg, '8.1f')} "
            f"{_fmt(v.pitch_deg, '6.1f')} {_fmt(v.roll_deg, '7.1f')} {_fmt(v.residual_ut, '8.2f')} "
            f"{_fmt(v.error_deg, '7.2f')}  {note[:60]}"
        )
    return lines


class Viewer:
    """Feeds DeviceViews from the messages and prints them (redrawn on a terminal, plain lines otherwise)."""

    def __init__(self, prefix: str, out: TextIO, tty: bool) -> None:
        self.prefix, self.out, self.tty = prefix, out, tty
        self.views: dict[str, DeviceView] = {}

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
            elif kind is wire.Kind.PROGRESS:
                message = wire.decode_progress(payload)
                self.view(message["device"]).on_progress(message)
            else:
                message = wire.unpack(payload, wire.CALIBRATION_LIMITS)
                self.view(str(message.get("device"))).on_calibration(message)
        except (wire.WireError, KeyError, TypeError, ValueError):
            pass  # the services count malformed input; the view just skips it

    def show(self, elapsed_s: float) -> None:
        lines = render_lines(self.views, elapsed_s)
        if self.tty:
            self.out.write("\x1b[H\x1b[2J" + "\n".join(lines) + "\n")
        else:
            self.out.write("\n".join(lines) + "\n\n")
        self.out.flush()
