"""The field left out where it disagrees with the heading (``HeadingGate``): a disturbance that turns the field
slowly, which the field's watch (``magnet.attitude.field_watch``) does not see, is caught by what it does to heading
(docs/compass.md, "Disturbances").

A parked car passed on the way turns the horizontal field by tens of degrees over a few seconds while |B| and the
dip hardly move (on a simulated walk: 28 deg of heading with |B| within 4 uT of the Earth's and the dip within 2 deg,
until its peak). The watch's steps, judged per radian the gyroscope turned, are too wide to see it in a swinging hand,
whose path over 2 s is 5-6 rad; vqf's own rejection judges |B| and the dip only. What does see it is the innovation
vqf corrects its heading by: each field sample turned into vqf's 6D Earth frame, its heading there less vqf's
magnetic heading offset (``delta``). Undisturbed, that disagreement is the tilt's error times tan(dip), the record's
leftover error and the gyroscope's drift since the last correction: a few degrees, a level this device usually has.
A world-fixed disturbance makes it grow while the gyroscope says the device did not turn: the gate leaves the
sample's field out (a zero row, which vqf skips: the gyroscope holds the heading) where the disagreement is more
than ``relative`` times its usual level (the ``percent`` percentile over blocks of 0.5 s, time constant ``tau_s``)
and more than ``floor_deg``.

Two things make the disagreement grow without a disturbance, and the gate yields to both:

- a calibration's leftover error bends heading by an amount that depends on the course, so after a corner the
  disagreement moves to another level: nothing is left out while the device turned more than ``turn_deg`` about
  the vertical within the last ``turn_s`` (the rotation about vqf's vertical of the gyroscope, less vqf's bias);
- a heading gone wrong (the gyroscope's drift while the field was left out): after ``max_reject_s`` of samples left
  out without a break the field is taken as right, and the gate stays open until a whole block agrees again.

Nothing is left out while vqf takes its first heading from the field (its ``kMagInit``: after the start and after a
new calibration) or before ``learn_s`` of agreeing samples have set the usual level. The samples are judged in the
turn gate's blocks (``magnet.attitude.turn_gate``), vqf's attitude, bias, delta and kMagInit read at each block's
start, so the answers do not depend on how the samples are batched. Compiled (``magnet._kernels.heading_gate_update``,
and within ``gated_run`` and ``fuse_rows``); tested against the plain maths.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from magnet.compiled import kernels as _kernels

#: the indices of the gate's settings and state arrays in ``magnet/_kernels.c``
_LAYOUT: dict[str, int] = _kernels.heading_gate_layout()


@dataclasses.dataclass(frozen=True)
class HeadingGateSettings:
    """The gate's rules (see the module docstring): a sample is left out where its disagreement with vqf's heading
    exceeds ``floor_deg`` and ``relative`` times the usual level (the ``percent`` percentile of a block's agreeing
    samples, followed with the time constant ``tau_s``) once ``learn_s`` of agreeing samples were seen, unless the
    device turned more than ``turn_deg`` about the vertical within the last ``turn_s``; held ``hold_s`` after; given
    up after ``max_reject_s`` without a break. Tuned on the simulator's walks past doors and parked cars, seeds
    1-8."""

    floor_deg: float = 12.0
    relative: float = 3.0
    percent: float = 90.0
    tau_s: float = 20.0
    learn_s: float = 5.0
    hold_s: float = 0.5
    max_reject_s: float = 5.0
    turn_deg: float = 30.0
    turn_s: float = 3.0
    smooth_s: float = 0.1

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"HeadingGateSettings.{field.name} must be a positive number, got {value!r}")
        if self.percent > 100.0:
            raise ValueError(f"HeadingGateSettings.percent must be within 0-100, got {self.percent!r}")


class HeadingGate:
    """The gate of the module docstring for one filter, causal, in blocks of ``BLOCK_S`` (the turn gate's): the
    settings and the state are float64 arrays (``settings_array``, ``state``) laid out as the C file's H_* and HS_*
    indices. ``update`` judges one piece within a block; ``magnet.attitude.turn_gate.run_gated`` and ``fuse_rows``
    run it with vqf. State: vqf's attitude, bias, delta and kMagInit of the block's start carried forward, the usual
    level, the samples it was learnt from, the hold, the run left out, the last ``turn_s`` of the rotation about the
    vertical, the block's disagreements; bounded."""

    BLOCK_S = 0.5

    def __init__(self, period_s: float, settings: HeadingGateSettings = HeadingGateSettings()) -> None:
        self.period_s, self.settings = float(period_s), settings
        self.block = max(1, round(self.BLOCK_S / self.period_s))
        self.turn_width = max(1, round(settings.turn_s / self.period_s))
        layout = _LAYOUT
        self.settings_array = np.zeros(layout["settings"])
        for key, value in (
            ("period", self.period_s),
            ("block", self.block),
            ("turn_width", self.turn_width),
            ("floor", np.radians(settings.floor_deg)),
            ("relative", settings.relative),
            ("percent", settings.percent),
            ("tau", settings.tau_s),
            ("learn", settings.learn_s),
            ("hold", round(settings.hold_s / self.period_s)),
            ("max_run", round(settings.max_reject_s / self.period_s)),
            ("turn", np.radians(settings.turn_deg)),
            ("smooth", -np.expm1(-self.period_s / settings.smooth_s)),
        ):
            self.settings_array[layout[key]] = value
        self.state = np.zeros(layout["ring"] + self.turn_width + self.block)
        self.reset()

    def reset(self) -> None:
        """Forget the past (the filter restarted; with the turn gate, whose blocks are the gate's)."""
        self.state[:] = 0.0
        self.state[_LAYOUT["attitude"]] = 1.0
        self.state[_LAYOUT["smoothed"]] = np.nan
        self.state[_LAYOUT["ring"] + self.turn_width :] = np.nan

    def forget_level(self) -> None:
        """The usual disagreement forgotten, as when the magnetic side restarts (the heading itself in question: the
        gyroscope lost a stall's rotation, ``magnet.compass.missed``): nothing is left out until ``learn_s`` of
        agreeing samples have set it again; the blocks go on as they were."""
        for key in ("level", "seen", "run", "hold_left", "accepting", "over"):
            self.state[_LAYOUT[key]] = 0.0
        self.state[_LAYOUT["smoothed"]] = np.nan

    @property
    def samples(self) -> int:
        """Samples judged since the start."""
        return int(self.state[_LAYOUT["samples"]])

    @property
    def level_deg(self) -> float:
        """The usual disagreement (deg; 0 until learnt)."""
        return float(np.degrees(self.state[_LAYOUT["level"]]))

    def update(
        self,
        gyr: np.ndarray,
        field: np.ndarray | None,
        start_wxyz: np.ndarray,
        bias: np.ndarray,
        delta_rad: float,
        k_mag_init: float,
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """(the field to feed vqf (n, 3), zero rows where left out (None without a field), (n,) bool: the samples
        left out) for one piece of body rates and field (n, 3) rad/s and uT in vqf's frame, within one block.
        ``start_wxyz`` (4,) vqf's 6D attitude, ``bias`` (3,) rad/s, ``delta_rad`` and ``k_mag_init`` vqf's (its state
        ``delta`` and ``kMagInit``) are read at a block's start only."""
        gyr = np.ascontiguousarray(gyr, dtype=float)
        if gyr.ndim != 2 or gyr.shape[1] != 3:
            raise ValueError(f"gyr must be (n, 3), got {gyr.shape}")
        flags = np.zeros(len(gyr), dtype=bool)
        given = None if field is None else np.ascontiguousarray(field, dtype=float)
        fed = np.empty((len(gyr), 3)) if given is not None else np.zeros((len(gyr), 3))
        start = np.ascontiguousarray(start_wxyz, dtype=float).reshape(4)
        _kernels.heading_gate_update(
            self.settings_array, self.state, gyr, given if given is not None else np.zeros((len(gyr), 3)), start,
            np.ascontiguousarray(bias, dtype=float).reshape(3), float(delta_rad), float(k_mag_init), fed, flags,
        )  # fmt: skip
        return (fed if given is not None else None), flags

    def judge(
        self, filter_: Any, gyr: np.ndarray, field: np.ndarray | None, start_wxyz: np.ndarray, bias: np.ndarray
    ) -> tuple[np.ndarray | None, np.ndarray]:
        """``update`` with vqf's ``delta`` and ``kMagInit`` read from ``filter_`` (a ``vqf.VQF``) at a block's start."""
        at_start = self.samples % self.block == 0
        delta, init = (float(filter_.getDelta()), float(filter_.state["kMagInit"])) if at_start else (0.0, 0.0)
        return self.update(gyr, field, start_wxyz, bias, delta, init)


def kernel_arrays(gate: HeadingGate | None) -> tuple[Any, Any]:
    """A heading gate's settings and state for ``magnet._kernels.gated_run`` and ``fuse_rows`` (None, None: none)."""
    return (None, None) if gate is None else (gate.settings_array, gate.state)
