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
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import vqf

from magnet.attitude.aided_fusion import carry_forward
from magnet.attitude.field_watch import to_frame

#: the outputs of vqf's ``updateBatch`` that the filters read, joined over the gate's pieces (``run_gated``)
BATCH_OUTPUTS = ("quat6D", "quat9D", "magDistDetected", "restDetected", "bias", "delta")


@dataclasses.dataclass(frozen=True)
class TurnSettings:
    """The gate's rules. Gait: over the last ``gait_s`` seconds the specific force's magnitude varies by more than
    ``gait_sd_ms2`` (standard deviation, m/s^2) and repeats itself (normalised autocorrelation over ``gait_corr``) at
    a lag of ``step_s`` (a step). In a gait the accelerometer is fed ``window_s`` late and left out where the rotation
    about the vertical, the mean over the window after the sample less that over the window before, exceeds
    ``turn_deg`` degrees, for at most ``max_hold_s`` seconds without a break."""

    window_s: float = 1.0
    turn_deg: float = 15.0
    max_hold_s: float = 8.0
    gait_s: float = 2.0
    gait_sd_ms2: float = 1.0
    gait_corr: float = 0.5
    step_s: tuple[float, float] = (0.3, 0.7)
    stride_s: tuple[float, float] = (0.55, 1.35)

    def __post_init__(self) -> None:
        for name in ("window_s", "turn_deg", "max_hold_s", "gait_s", "gait_sd_ms2", "gait_corr"):
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
    (``gait_s``) are a gait. ``update`` takes body rates and specific forces in vqf's frame (n, 3) rad/s and m/s^2
    and returns the accelerometer to feed vqf. Outside a gait: the samples' own. In a gait: each sample's specific
    force of ``window_s`` earlier, turned into the body's present axes by the gyroscope's integration between them,
    or a zero vector where the course turned around that earlier sample. State: the last 2 window - 1 samples'
    rotations about the vertical (rad), their specific forces in the frame the gyroscope's integration holds still,
    that integration, the last ``gait_s`` of |specific force|, the block's attitude and bias, the samples gated
    without a break; bounded."""

    BLOCK_S = 0.5

    def __init__(
        self, period_s: float, settings: TurnSettings = TurnSettings(), filter_params: Mapping[str, Any] | None = None
    ) -> None:
        self.period_s, self.settings = float(period_s), settings
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
        self.reset()

    def reset(self) -> None:
        """Forget the past (the filter restarted)."""
        #: the last 2 (width - 1) samples' rotations about the vertical, rad
        self.recent = np.zeros(2 * (self.width - 1))
        self.stride = self.width  # samples of the last gait's stride (two steps)
        self.earth_acc = np.full((self.width - 1, 3), np.nan)  # the last samples' specific force, integrated frame
        self.run = 0  # samples gated without a break up to now
        self.held = np.array([1.0, 0.0, 0.0, 0.0])  # the gyroscope's integration from the start (its own frame)
        self.magnitudes = np.full(self.gait_width, np.nan)  # the last gait_s of |specific force|, m/s^2
        self.attitude = np.array([1.0, 0.0, 0.0, 0.0])  # vqf's 6D attitude carried forward through the block
        self.bias = np.zeros(3)  # vqf's bias at the block's start, rad/s
        self.in_gait = False  # the block is within a gait
        self.samples = 0
        if self.alone is not None:
            self.alone.reset()

    def left_in_block(self) -> int:
        """Samples until the present block ends (a batch is cut there, vqf's state taken at the next start)."""
        return self.block - self.samples % self.block

    def update(
        self, gyr: np.ndarray, acc: np.ndarray, start_wxyz: np.ndarray, bias: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(the accelerometer to feed (n, 3), (n,) bool: the samples fed a zero vector because the course turned
        around the earlier sample fed in their place); see the class docstring. ``start_wxyz`` and ``bias`` are
        read at a block's start only; gyr and acc (n, 3) must not reach past the block's end."""
        gyr, acc = np.asarray(gyr, dtype=float), np.asarray(acc, dtype=float)
        if len(gyr) == 0:
            return np.zeros((0, 3)), np.zeros(0, dtype=bool)
        if len(gyr) > self.left_in_block():
            raise ValueError(f"a batch for the turn gate must end within its block: {self.left_in_block()} samples")
        if self.samples % self.block == 0:
            self.attitude = np.asarray(start_wxyz, dtype=float)
            self.bias = np.asarray(bias, dtype=float)
            self.in_gait = self._gait()
        self.samples += len(gyr)
        attitude = carry_forward(self.attitude, gyr, self.bias, self.period_s)
        self.attitude = attitude[-1]
        vertical = to_frame(attitude, gyr - self.bias)[:, 2] * self.period_s
        seen = np.concatenate([self.recent, vertical])
        self.recent = seen[len(vertical) :]
        turned = self._turned(seen, len(vertical))
        held = carry_forward(self.held, gyr, self.bias, self.period_s)  # the gyroscope's own turns, never corrected
        self.held = held[-1] / np.linalg.norm(held[-1])
        earth = np.concatenate([self.earth_acc, to_frame(held, acc)])
        delayed, self.earth_acc = earth[: len(acc)], earth[len(acc) :]
        self.magnitudes = np.concatenate([self.magnitudes, np.sqrt(np.sum(acc * acc, axis=1))])[-self.gait_width :]
        over = np.abs(np.degrees(turned)) > self.settings.turn_deg
        gated = self._held(over & self.in_gait)
        if not self.in_gait:
            return acc, gated
        inverse = held * np.array([1.0, -1.0, -1.0, -1.0])
        fed = to_frame(inverse, delayed)
        fresh = np.isnan(fed[:, 0])  # the first window after a start: the sample itself, not yet delayed
        fed[fresh] = acc[fresh]
        fed[gated] = 0.0
        return np.ascontiguousarray(fed), gated

    def _turned(self, seen: np.ndarray, count: int) -> np.ndarray:
        """(count,) rad: about the vertical, the mean yaw over the stride after each delayed sample (``width - 1``
        back from each of the last ``count`` of ``seen``, the rotations per sample) less the mean over the stride
        before it. A triangle of weights over the 2 stride - 1 rotations centred on it: whole strides, so that what
        turns back within a stride (the trunk's yaw, a swinging limb) cancels out, whatever its shape."""
        n = self.stride
        ramp = np.arange(1, n + 1, dtype=float) / n
        kernel = np.concatenate([ramp, ramp[-2::-1]])
        first = len(seen) - count - (self.width - 1) - (n - 1)  # the first delayed sample's window start
        return np.convolve(seen[first : len(seen) - (self.width - 1) + n - 1], kernel, mode="valid")

    def _gait(self) -> bool:
        """Whether the last ``gait_s`` of samples are a gait: |specific force| varying by more than ``gait_sd_ms2``
        and repeating itself at a step's or a stride's lag (normalised autocorrelation over ``gait_corr``: a runner's
        swinging hand repeats itself at the stride more than at the step). In a gait, the stride
        (samples) is the lag of ``stride_s`` where |specific force| repeats itself best (a stride, left and right
        steps, is the gait's period)."""
        if np.isnan(self.magnitudes[0]):
            return False
        centred = self.magnitudes - self.magnitudes.mean()
        power = float(np.dot(centred, centred))
        if power <= len(centred) * self.settings.gait_sd_ms2**2:
            return False
        correlation = np.correlate(centred, centred, mode="full")[len(centred) - 1 :]
        strides = self.stride_lags[self.stride_lags < len(centred)]
        if max(correlation[self.lags].max(), correlation[strides].max()) <= self.settings.gait_corr * power:
            return False
        self.stride = min(self.width, int(strides[np.argmax(correlation[strides])]))
        return True

    def _held(self, turning: np.ndarray) -> np.ndarray:
        """``turning`` less the samples past ``max_hold`` of a run without a break (counted across batches)."""
        at = np.arange(len(turning))
        last_off = np.maximum.accumulate(np.where(turning, -1, at))
        run = np.where(turning, np.where(last_off >= 0, at - last_off, at + 1 + self.run), 0)
        self.run = int(run[-1])
        return turning & (run <= self.max_hold)


def run_gated(
    gate: TurnGate,
    filter_: Any,
    piece: Callable[[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray], dict[str, Any]],
    samples: tuple[np.ndarray, np.ndarray, np.ndarray | None],
    watched: np.ndarray,
) -> dict[str, Any]:
    """One batch (gyroscope, accelerometer, field or None; (N, 3) each, vqf's frames) through ``piece`` (vqf's
    ``updateBatch`` or its bias loop, with ``watched`` (N,) the samples the field's watch left out) in pieces cut at
    the gate's blocks, each fed the accelerometer the gate gives, reading the attitude and the bias of ``filter_``
    (a ``vqf.VQF``) at each block's start: ``piece``'s outputs for the whole batch (``BATCH_OUTPUTS`` joined)."""
    gyr, acc, field = samples
    outs, start = [], 0
    while start < len(gyr):
        part = slice(start, start + gate.left_in_block())
        bias = np.asarray(filter_.getBiasEstimate()[0], dtype=float)
        fed, _ = gate.update(gyr[part], acc[part], np.asarray(filter_.getQuat6D(), dtype=float), bias)
        outs.append(piece(gyr[part], fed, None if field is None else field[part], watched[part]))
        start = part.stop
    if len(outs) == 1:
        joined = outs[0]
    else:
        joined = {
            key: np.concatenate([np.asarray(out[key]) for out in outs]) for key in BATCH_OUTPUTS if key in outs[0]
        }
    return joined if gate.alone is None else gate.alone.answer(joined, gyr, acc, field)


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
