"""The accelerometer left out while the course turns (``TurnGate``): a filter's tilt is the low-passed specific force,
which is gravity only while the device's velocity is steady (docs/compass.md, "Turns of the course").

A walker or a runner turning a corner at speed v changes its velocity by 2 v sin(theta / 2) within a second or two
(4.7 m/s for a 90 deg corner at 3.3 m/s): a centripetal acceleration of v x the course rate, horizontal, that vqf's
accelerometer low-pass (a second-order filter of tauAcc = 3 s) takes for gravity leaning. Its peak answer to that
velocity change is about 0.21 /s x 4.7 m/s = 1 m/s^2, a tilt of 6 deg, and the tilt's error times tan(dip) bends the
heading. The gait's accelerations (several m/s^2 at the step rate) average out in that low-pass; the corners do
not. On fieldsim's running (seed 2026) with the true calibration, the filter's tilt error followed the low-passed
true linear acceleration (3.07 against 3.04 deg RMS), and with gravity alone in the accelerometer its heading was
0.42 deg RMS instead of 5.02.

A turn of the course shows as the device turning about the vertical for longer than a stride: the rotation about
the Earth's vertical (the body rate, less vqf's bias, turned into the Earth frame by vqf's 6D attitude carried
forward through the batch) summed over the last ``window_s``. Where it exceeds ``turn_deg`` the accelerometer's
sample is left out (a zero vector, which vqf skips: the gyroscope holds the tilt meanwhile, its bias learnt). The
window spans at least a stride (about 0.7 s running, 1.1 s walking), so the trunk's yaw at the stride frequency and
a swinging limb's rotation, which turn back within it, sum to little; a corner of 45 deg or more at a course rate of
60 deg/s and more exceeds it within a fraction of a second. A turn held for longer than ``max_hold_s`` (a device
spinning on a turntable, a robot turning on the spot, a vehicle circling) gets the accelerometer back: the
gyroscope alone must not hold the tilt for ever.

A swinging hand is no gait (its |specific force| does not repeat at a step's lag) but its body rates swing: over
the last ``gait_s`` their spread about their mean (RMS of the vector) is between ``swing_sd_rads`` and
``swing_max_rads`` and repeats at a stride's lag (a runner's arm too, since 4 Dec: 4.6-6.9 rad/s). There leaving
samples out would cut the arm's own accelerations (10 m/s^2 and more at the ends of the swing, periodic: they
average out over whole strides only) at arbitrary phases. So in a swing the samples are fed as they come, and where
the course turned over the last two strides each is *levelled*: less the horizontal part (square to vqf's vertical)
of the specific force's mean over the last stride, in the frame the gyroscope holds still. Over a stride the arm's
accelerations cancel and gravity is constant in that frame, so that horizontal part is the course's own
(centripetal) acceleration; the swing's stays in, as on the straights.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import vqf

from magnet.attitude.heading_gate import HeadingGate, kernel_arrays
from magnet.compiled import kernels as _kernels

#: the indices of the gate's settings and state arrays in ``magnet/_kernels.c``
_LAYOUT: dict[str, int] = _kernels.gate_layout()
#: the outputs of vqf's ``updateBatch`` that the filters read, joined over the gate's pieces (``run_gated``)
BATCH_OUTPUTS = ("quat6D", "quat9D", "magDistDetected", "restDetected", "bias", "delta")


@dataclasses.dataclass(frozen=True)
class TurnSettings:
    """The gate's rules. Gait: over the last ``gait_s`` seconds the specific force's magnitude varies by more than
    ``gait_sd_ms2`` (standard deviation, m/s^2) and repeats itself (normalised autocorrelation over ``gait_corr``) at
    a lag of ``step_s`` (a step). In a gait the accelerometer is fed ``window_s`` late and left out where the rotation
    about the vertical, the mean over the window after the sample less that over the window before, exceeds
    ``turn_deg`` degrees, for at most ``max_hold_s`` seconds without a break. Swing (judged first): over ``gait_s``
    the body rates' spread (RMS of the vector about its mean) between ``swing_sd_rads`` and ``swing_max_rads``
    rad/s, repeating (summed products over ``swing_corr`` times the power) at a lag of ``stride_s``, the magnitudes a
    gait too from ``swing_gait_rads`` on (a runner's arm, not a device turned fast by hand); in a swing the samples
    come as they are, levelled where the rotation about the vertical over the last two strides (triangle-weighted)
    exceeds ``turn_deg``, for at most ``max_hold_s``."""

    window_s: float = 1.0
    turn_deg: float = 15.0
    max_hold_s: float = 8.0
    gait_s: float = 2.0
    gait_sd_ms2: float = 1.0
    gait_corr: float = 0.5
    step_s: tuple[float, float] = (0.3, 0.7)
    stride_s: tuple[float, float] = (0.55, 1.35)
    swing_sd_rads: float = 2.2
    swing_max_rads: float = 8.0
    swing_corr: float = 0.25
    swing_gait_rads: float = 4.0

    def __post_init__(self) -> None:
        for name in [field.name for field in dataclasses.fields(self) if field.name not in ("step_s", "stride_s")]:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"TurnSettings.{name} must be a positive number of its unit, got {value!r}")
        low, high = self.step_s
        if not 0 < low < high < self.gait_s:
            raise ValueError(
                f"TurnSettings.step_s must be (shortest, longest) step in s within gait_s, got {self.step_s}"
            )


class TurnGate:
    """The gate of the module docstring for one filter, causal and batch by batch. The samples are judged in blocks
    of ``BLOCK_S`` counted from the start, so that the answers are the same however the samples are batched: the
    caller (``magnet.attitude.fusion.Fusion``) cuts its batches at the blocks' ends (``left_in_block``). At a block's
    start the gate takes vqf's 6D attitude (4,) wxyz (body -> its Earth frame, z up) and its gyroscope bias (3,)
    rad/s, carries them forward through the block with the gyroscope, and judges whether the samples before it
    (``gait_s``) are a swing, else a gait. ``update`` takes body rates and specific forces in vqf's frame (n, 3)
    rad/s and m/s^2 and returns the accelerometer to feed vqf. Outside a gait and a swing: the samples' own. In a
    gait: each sample's specific force of ``window_s`` earlier, turned into the body's present axes by the
    gyroscope's integration between them, or a zero vector where the course turned around that earlier sample. In a
    swing: each sample's own, levelled where the course turned over the two strides before it. State: the last
    2 window - 1 samples' rotations about the vertical (rad), their specific forces in the frame the gyroscope's
    integration holds still, that integration, the last ``gait_s`` of |specific force| and of body rates, the
    block's attitude and bias, the samples gated (or levelled) without a break; bounded. The windows are rings in the
    state (a piece writes its own samples only), read oldest first through the attributes below.

    The per-sample maths is compiled (``magnet._kernels.gate_update``; ``run_gated`` runs a whole batch and vqf in one
    call, ``gated_run``): the settings and the state are float64 arrays (``settings``, ``state``) laid out as the C
    file's T_* and G_* indices (``_LAYOUT``); the attributes below read them."""

    BLOCK_S = 0.5

    def __init__(
        self, period_s: float, settings: TurnSettings = TurnSettings(), filter_params: Mapping[str, Any] | None = None
    ) -> None:
        self.period_s, self.settings = float(period_s), settings
        #: the field's heading gate, judged in this gate's blocks and reset with it (``magnet.attitude.heading_gate``)
        self.heading: HeadingGate | None = None
        #: with ``filter_params`` (vqf's, as the gated filter's), vqf without the gate (``Alone``): its 6D attitude is
        #: the answer until a field reaches the filter
        self.alone = None if filter_params is None else Alone(self.period_s, filter_params)
        self.gait_width = max(3, round(settings.gait_s / self.period_s))
        self.lags, self.stride_lags = (
            np.arange(max(1, round(low / self.period_s)), max(1, round(high / self.period_s)) + 1)
            for low, high in (settings.step_s, settings.stride_s)
        )
        #: the delay (samples): the longest stride judged, at least ``window_s``
        self.width = max(round(settings.window_s / self.period_s), int(self.stride_lags[-1]))
        self.max_hold = max(1, round(settings.max_hold_s / self.period_s))
        self.block = max(1, round(self.BLOCK_S / self.period_s))
        layout = _LAYOUT
        self.settings_array = np.zeros(layout["settings"])
        for key, value in (
            ("period", self.period_s),
            ("width", self.width),
            ("gait_width", self.gait_width),
            ("lag_lo", self.lags[0]),
            ("lag_hi", self.lags[-1]),
            ("stride_lo", self.stride_lags[0]),
            ("stride_hi", self.stride_lags[-1]),
            ("max_hold", self.max_hold),
            ("block", self.block),
            ("turn_deg", settings.turn_deg),
            ("gait_sd", settings.gait_sd_ms2),
            ("gait_corr", settings.gait_corr),
            ("swing_sd", settings.swing_sd_rads),
            ("swing_max", settings.swing_max_rads),
            ("swing_corr", settings.swing_corr),
            ("swing_gait", settings.swing_gait_rads),
        ):
            self.settings_array[layout[key]] = value
        recent = layout["recent"]
        self._parts = (
            recent,
            recent + 2 * (self.width - 1),
            recent + 5 * (self.width - 1),
            recent + 5 * (self.width - 1) + self.gait_width,
        )
        self.state = np.zeros(self._parts[3] + 3 * self.gait_width)
        self.reset()

    def reset(self) -> None:
        """Forget the past (the filter restarted)."""
        layout, state = _LAYOUT, self.state
        state[:] = 0.0
        state[layout["stride"]] = self.width  # samples of the last gait's stride (two steps)
        state[layout["held"]] = 1.0  # the gyroscope's integration from the start (its own frame)
        state[layout["attitude"]] = 1.0  # vqf's 6D attitude carried forward through the block
        state[self._parts[1] :] = np.nan  # the specific forces, magnitudes and rates not seen yet
        if self.alone is not None:
            self.alone.reset()
        if self.heading is not None:
            self.heading.reset()

    @property
    def samples(self) -> int:
        """Samples judged since the start."""
        return int(self.state[_LAYOUT["samples"]])

    @property
    def stride(self) -> int:
        """Samples of the last gait's or swing's stride (two steps); ``width`` before any."""
        return int(self.state[_LAYOUT["stride"]])

    @property
    def in_gait(self) -> bool:
        """Whether the present block is within a gait."""
        return bool(self.state[_LAYOUT["in_gait"]])

    @property
    def in_swing(self) -> bool:
        """Whether the present block is within a swing (outside a gait)."""
        return bool(self.state[_LAYOUT["in_swing"]])

    @property
    def run(self) -> int:
        """Samples gated without a break up to now."""
        return int(self.state[_LAYOUT["run"]])

    def _ring(self, part: int, columns: int) -> np.ndarray:
        """Part ``part`` of the state's tail, a ring of rows of ``columns`` whose oldest row is at ``samples``
        modulo its length (``magnet/_kernels.c``, ``ring_head``), oldest first (a copy)."""
        stop = self._parts[part + 1] if part + 1 < len(self._parts) else len(self.state)
        rows = self.state[self._parts[part] : stop].reshape(-1, columns)
        return np.roll(rows, -(self.samples % len(rows)) if len(rows) else 0, axis=0)

    @property
    def recent(self) -> np.ndarray:
        """The last 2 (width - 1) samples' rotations about the vertical (rad), oldest first (a copy)."""
        return self._ring(0, 1).reshape(-1)

    @property
    def earth_acc(self) -> np.ndarray:
        """The last width - 1 samples' specific forces (width - 1, 3) in the integrated frame (NaN: not seen)."""
        return self._ring(1, 3)

    @property
    def magnitudes(self) -> np.ndarray:
        """The last ``gait_s`` of |specific force| (gait_width,) m/s^2, oldest first (NaN: not seen)."""
        return self._ring(2, 1).reshape(-1)

    @property
    def rates(self) -> np.ndarray:
        """The last ``gait_s`` of body rates (gait_width, 3) rad/s as measured, oldest first (NaN: not seen)."""
        return self._ring(3, 3)

    def left_in_block(self) -> int:
        """Samples until the present block ends (a batch is cut there, vqf's state taken at the next start)."""
        return self.block - self.samples % self.block

    def update(
        self, gyr: np.ndarray, acc: np.ndarray, start_wxyz: np.ndarray, bias: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(the accelerometer to feed (n, 3), (n,) bool: the samples fed a zero vector because the course turned
        around the earlier sample fed in their place; none in a swing, where samples are levelled instead); see the
        class docstring. ``start_wxyz`` and ``bias`` are
        read at a block's start only; gyr and acc (n, 3) must not reach past the block's end."""
        gyr = np.ascontiguousarray(gyr, dtype=float)
        acc = np.ascontiguousarray(acc, dtype=float)
        if len(gyr) == 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=bool)
        if len(gyr) > self.left_in_block():
            raise ValueError(f"a batch for the turn gate must end within its block: {self.left_in_block()} samples")
        if acc.shape != gyr.shape or gyr.ndim != 2 or gyr.shape[1] != 3:
            raise ValueError(f"gyr and acc must be (n, 3) each, got {gyr.shape} and {acc.shape}")
        fed, gated = np.empty_like(acc), np.empty(len(acc), dtype=bool)
        start = np.ascontiguousarray(start_wxyz, dtype=float).reshape(4)
        changed = _kernels.gate_update(
            self.settings_array, self.state, gyr, acc, start, np.ascontiguousarray(bias, dtype=float).reshape(3),
            fed, gated,
        )  # fmt: skip
        return (fed if changed else acc), gated


def run_gated(
    gate: TurnGate,
    filter_: Any,
    piece: Callable[[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray], dict[str, Any]] | None,
    samples: tuple[np.ndarray, np.ndarray, np.ndarray | None],
    watched: np.ndarray,
) -> dict[str, Any]:
    """One batch (gyroscope, accelerometer, field or None; (N, 3) each, vqf's frames) through ``piece`` (vqf's
    ``updateBatch`` or its bias loop, with ``watched`` (N,) the samples the field's watch left out) in pieces cut at
    the gate's blocks, each fed the accelerometer the gate gives, reading the attitude and the bias of ``filter_``
    (a ``vqf.VQF``) at each block's start: ``piece``'s outputs for the whole batch (``BATCH_OUTPUTS`` joined).
    ``piece`` None: vqf's ``updateBatch``, the whole batch in one compiled call (``run_gated_vqf``). The samples the
    gate's ``heading`` gate leaves out reach the piece as zero rows, flagged disturbed."""
    gyr, acc, field, heading = *samples, gate.heading
    if piece is None:
        joined = run_gated_vqf(gate, filter_, samples)
        return joined if gate.alone is None else gate.alone.answer(joined, gyr, acc, field)
    outs, start = [], 0
    while start < len(gyr):
        part = slice(start, start + gate.left_in_block())
        bias = np.asarray(filter_.getBiasEstimate()[0], dtype=float)
        quat6 = np.asarray(filter_.getQuat6D(), dtype=float)
        fed, _ = gate.update(gyr[part], acc[part], quat6, bias)
        piece_field, flags = None if field is None else field[part], np.zeros(len(fed), dtype=bool)
        if heading is not None:
            piece_field, flags = heading.judge(filter_, gyr[part], piece_field, quat6, bias)
        out = piece(gyr[part], fed, piece_field, watched[part] | flags)
        if flags.any():
            out = {**out, "magDistDetected": np.asarray(out["magDistDetected"], dtype=bool) | flags}
        outs.append(out)
        start = part.stop
    if len(outs) == 1:
        joined = outs[0]
    else:
        joined = {
            key: np.concatenate([np.asarray(out[key]) for out in outs]) for key in BATCH_OUTPUTS if key in outs[0]
        }
    return joined if gate.alone is None else gate.alone.answer(joined, gyr, acc, field)


@functools.cache
def bind_vqf() -> None:
    """Find vqf's compiled filter (its C++ class, in vqf's own extension module) for ``run_gated_vqf``."""
    _kernels.vqf_bind(str(sys.modules[vqf.VQF.__module__].__file__))


def run_gated_vqf(
    gate: TurnGate, filter_: Any, samples: tuple[np.ndarray, np.ndarray, np.ndarray | None]
) -> dict[str, Any]:
    """``run_gated`` with vqf's ``updateBatch`` for the piece, in one compiled call (``magnet._kernels.gated_run``:
    the same gate, the same vqf object driven through its C++ class): vqf's outputs quat9D (N, 4) (and quat6D without
    a field; with one nobody reads it), restDetected and magDistDetected (N,) bool for the batch (gyroscope,
    accelerometer, field or None; (N, 3) each, vqf's frames, C-contiguous float64); the gate's ``heading`` gate
    leaves samples out as ``run_gated`` says."""
    bind_vqf()
    gyr, acc, field = samples
    count = len(gyr)
    out = {
        "quat9D": np.empty((count, 4)),
        "restDetected": np.empty(count, dtype=bool),
        "magDistDetected": np.empty(count, dtype=bool),
    }
    if field is None:
        out["quat6D"] = np.empty((count, 4))
    _kernels.gated_run(
        filter_, gate.settings_array, gate.state, gyr, acc, field,
        out.get("quat6D"), out["quat9D"], out["restDetected"], out["magDistDetected"],
        *kernel_arrays(gate.heading),
    )  # fmt: skip
    return out


def fuse_rows(
    gate: TurnGate, filter_: Any, watch: Any, inputs: tuple[np.ndarray, ...], lo: int, hi: int, quat: Any, out: Any
) -> None:
    """Rows lo .. hi of a drain's gyroscope, accelerometer and field (S, 3) each (vqf's frames, finite, C-contiguous
    float64) through the field's ``watch`` (a ``FieldWatch`` or None), its flagged samples' field left out, then
    ``run_gated_vqf``, in one compiled call (``magnet._kernels.fuse_rows``: the code of ``watch_update`` and
    ``gated_run``): vqf's quaternions written into rows lo .. hi of ``quat`` (S, 4), its disturbance flags or-ed with
    the watch's into those of ``out`` (S,) bool; the gate's ``heading`` gate leaves samples out too.
    ``Fusion.update_rows`` calls it."""
    bind_vqf()
    gyr, acc, field = inputs
    args = None if watch is None else watch.kernel_args
    arrays = kernel_arrays(gate.heading)
    _kernels.fuse_rows(filter_, gate.settings_array, gate.state, args, gyr, acc, field, lo, hi, quat, out, *arrays)


class Alone:
    """vqf without the gate, beside the gated filter until a field reaches it: its 6D attitude is the filter's answer
    until then (docs/compass.md, "Turns of the course").

    Without the field the heading is the gyroscope's integrated, and its error is the integral of the error of vqf's
    gyroscope bias about the vertical (within 0.1-0.3 deg of it on the simulated walks), which a walker's motion
    leaves unobserved; the tilt, which the gate keeps right, does not enter it. The gate changes the accelerometer
    vqf's bias is learnt from, and with it which share of that unobserved bias is left: on a given walk better or
    worse, by chance (600 s walks, seeds 1-6, heading RMS without vs with the gate: running 27.7 / 30.2 deg,
    texting 23.2 / 23.2, pocket 50.2 / 48.9, phoning 28.6 / 29.3). So until the field is used the answer is plain
    vqf's, the gyroscope alone as any filter has it; the gated filter runs on beside it, its tilt and bias (which
    the field's heading needs: leaving the gate out until then made the running walks' heading after their first
    record worse, 2.05 -> 2.46 deg, seeds 1-6) ready when the field comes. Then this filter is dropped (``done``)."""

    def __init__(self, period_s: float, params: Mapping[str, Any]) -> None:
        self.period_s, self.params = period_s, dict(params)
        self.filter: Any = None
        self.reset()

    def reset(self) -> None:
        """From the start again (the filter restarted)."""
        self.filter = vqf.VQF(self.period_s, **self.params)

    @property
    def done(self) -> bool:
        """Whether a field has reached the filter since the start (then this filter no longer runs)."""
        return self.filter is None

    def answer(self, out: dict[str, Any], gyr: np.ndarray, acc: np.ndarray, field: np.ndarray | None) -> dict[str, Any]:
        """The gated filter's outputs ``out`` for one batch (gyr, acc (N, 3) as they came, field (N, 3) or None, a
        zero row where it is left out; vqf's frames) with its attitudes (quat6D, quat9D) replaced by this filter's
        6D attitude up to the first sample with a field, after which this filter is dropped."""
        if self.filter is None:
            return out
        used = np.zeros(len(gyr), dtype=bool) if field is None else np.any(field != 0.0, axis=1)
        first = int(np.argmax(used)) if used.any() else len(gyr)
        if first == 0:
            self.filter = None
            return out
        alone = np.asarray(self.filter.updateBatch(gyr[:first], acc[:first])["quat6D"], dtype=float)
        if first < len(gyr):
            self.filter = None
        joined = dict(out)
        for key in ("quat6D", "quat9D"):
            if key in joined:
                quat = np.array(joined[key], dtype=float)
                quat[:first] = alone
                joined[key] = quat
        return joined
