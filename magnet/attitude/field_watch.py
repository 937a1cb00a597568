"""A watch over the field (``FieldWatch``): which samples a passing disturbance (a steel door, a parked car, a magnet)
changes, causal and batch by batch, so that the attitude filter leaves them out and holds its heading on the
gyroscope meanwhile (``magnet.attitude.fusion.Fusion(..., watch=True)``, off by default for its cost;
docs/compass.md, "Disturbances").

The field is turned into the frame the gyroscope's integration holds still (w_k = Q_k b_k, Q_k the attitude
integrated from the filter's start), where the Earth's field is constant: a change of w over a window that the
rotation does not explain is a disturbance coming or going, whatever its direction (a horizontal turn of the field,
which neither |B| nor dip sees, is the one that turns the heading). With |B| against its running reference, those
statistics are judged against the usual level each has on this device (learnt from the samples, as vqf learns its
own reference): a calibration's leftover error, which shows as steps of about |e| x the angle turned in a window,
raises the usual level and with it what counts as unusual, so an imperfect calibration is not taken for a
disturbance. A field flagged without a break for longer than ``max_reject_s`` is the new normal (another place, or
another calibration): accepted, and learnt again. ``magnet.quality.disturbance.field_disturbance`` judges a whole
log with the same rotation-compensated steps (for fits).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.attitude.heading import row_norm


def _multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton products of rows (n, 4) wxyz (``frames.quaternion_multiply``, column by column: the watch's hot
    path runs on batches of a few samples, where numpy's per-call cost is most of the time)."""
    pw, px, py, pz = p[:, 0], p[:, 1], p[:, 2], p[:, 3]
    qw, qx, qy, qz = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    out = np.empty((len(p), 4))
    out[:, 0] = pw * qw - px * qx - py * qy - pz * qz
    out[:, 1] = pw * qx + px * qw + py * qz - pz * qy
    out[:, 2] = pw * qy - px * qz + py * qw + pz * qx
    out[:, 3] = pw * qz + px * qy - py * qx + pz * qw
    return out


def integrated_attitude(gyr_rads: np.ndarray, period_s: float, start: np.ndarray | None = None) -> np.ndarray:
    """Q (N, 4) wxyz: the attitude from integrating body rates gyr (N, 3) rad/s, q_k = q_{k-1} exp(w_k dt), from
    ``start`` (the attitude before the first sample; identity by default). All prefix products at once (log2 N
    passes of a scan)."""
    rotation = np.asarray(gyr_rads, dtype=float) * period_s
    angle = np.sqrt(np.sum(rotation * rotation, axis=1))
    half = 0.5 * angle
    scale = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0), 0.5)
    out = np.empty((len(rotation), 4))
    out[:, 0] = np.cos(half)
    out[:, 1:] = rotation * scale[:, None]
    if len(out) == 0:
        return out
    if start is not None:
        out[:1] = _multiply(np.asarray(start, dtype=float).reshape(1, 4), out[:1])
    stride = 1
    while stride < len(out):
        out[stride:] = _multiply(out[:-stride], out[stride:])
        stride *= 2
    return out / np.sqrt(np.sum(out * out, axis=1))[:, None]


def to_frame(quat_wxyz: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Body vectors (N, 3) in the integrated frame: R(q_k) v_k = v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)."""
    w, u = quat_wxyz[:, :1], quat_wxyz[:, 1:]
    v = np.asarray(vectors, dtype=float)
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products (n, 3) (np.cross's general path costs more than the arithmetic here)."""
    out = np.empty_like(b)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


@dataclasses.dataclass(frozen=True)
class WatchSettings:
    """The causal watch's rules (``FieldWatch``): the step windows with their floors ((window_s, floor_ut), ...)
    over means of smooth_s; a statistic is unusual above ``relative`` times its usual level (and its floor); |B|
    is unusual beyond field_tol_pct % of its running reference (or ``relative`` times its usual deviation); nothing
    is flagged before learn_s of samples; the reference and the usual levels follow undisturbed samples with the
    time constant level_tau_s; flagged samples are held flagged for hold_s after; a field flagged longer than
    max_reject_s without a break is the new normal (the place, or the calibration), accepted and learnt again. A
    step's usual level is per radian the gyroscope turned within its window (the length of its path, plus
    turn_floor_rad): a leftover calibration error, the magnetometer's lag behind the gyroscope and the gyroscope's
    scale error all change the field in the gyroscope's frame in proportion to the turning, so fast turns are
    judged by what the device usually shows when it turns as fast."""

    steps: tuple[tuple[float, float], ...] = ((0.25, 2.5), (2.0, 3.5))
    smooth_s: float = 0.1
    relative: float = 4.0
    field_tol_pct: float = 8.0
    learn_s: float = 5.0
    level_tau_s: float = 20.0
    hold_s: float = 0.5
    max_reject_s: float = 10.0
    turn_floor_rad: float = 0.25


class FieldWatch:
    """``field_disturbance``'s steps and magnitude, causal and batch by batch, for one device's filter: ``update``
    takes the corrected field and the gyroscope (N, 3) (any one body frame; rad/s) and says which samples are
    disturbed. Its references are its own (learnt from the samples, as vqf learns its own: a calibration's leftover
    error raises the usual levels, and with them what counts as unusual). The samples are judged in blocks of
    ``BLOCK_S`` counted from the start, the references moving at each block's end, so the flags are the same however
    the samples are batched. State: the integrated attitude, the last seconds of the field in its frame, the
    references and levels, the hold; bounded."""

    BLOCK_S = 0.5

    def __init__(self, period_s: float, settings: WatchSettings = WatchSettings()) -> None:
        self.period_s, self.settings = float(period_s), settings
        self.widths = [max(1, round(window / self.period_s)) for window, _ in settings.steps]
        self.smooth = max(1, round(settings.smooth_s / self.period_s))
        self.hold = round(settings.hold_s / self.period_s)
        self.block = max(1, round(self.BLOCK_S / self.period_s))
        self.reset()

    def reset(self) -> None:
        """Forget everything (the filter restarted)."""
        self.quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.tail = np.zeros((0, 3))
        self.tail_turn = np.zeros(0)
        self.turned = 0.0
        self.samples = 0
        self.reference_ut = 0.0
        self.levels = np.zeros(len(self.widths) + 1)  # usual step statistics, then usual | |B| - reference |
        self.hold_left = 0
        self.flagged_run = 0  # flagged samples in a row up to the last one
        self.pending: list[tuple[np.ndarray, np.ndarray]] = []  # this block's statistics and calm norms so far

    def _statistics(self, field: np.ndarray, gyr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((n, steps + 1), (n, steps)): each window's change of the smoothed field in the integrated frame (NaN
        where the history is too short), then | |B| - reference |; and each window's turn (rad, + turn_floor_rad)."""
        quat = integrated_attitude(gyr, self.period_s, self.quat)
        self.quat = quat[-1]
        world = np.concatenate([self.tail, to_frame(quat, field)])
        travelled = self.turned + np.cumsum(row_norm(gyr)) * self.period_s  # rad turned since the start
        self.turned = float(travelled[-1])
        turns = np.concatenate([self.tail_turn, travelled])
        sums = np.concatenate([np.zeros((1, 3)), np.cumsum(world, axis=0)])
        index = np.arange(len(world))
        low = np.maximum(index + 1 - self.smooth, 0)
        smooth = (sums[index + 1] - sums[low]) / (index + 1 - low)[:, None]
        new = index[len(self.tail) :]
        out = np.full((len(field), len(self.widths) + 1), np.nan)
        turned = np.ones((len(field), len(self.widths)))
        for j, width in enumerate(self.widths):
            valid = new - width >= self.smooth - 1
            now, then = new[valid], new[valid] - width
            out[valid, j] = row_norm(smooth[now] - smooth[then])
            turned[valid, j] = turns[now] - turns[then] + self.settings.turn_floor_rad  # the path, not the net turn
        out[:, -1] = np.abs(row_norm(field) - self.reference_ut)
        keep = max(self.widths) + self.smooth
        self.tail, self.tail_turn = world[-keep:], turns[-keep:]
        return out, turned

    def _held(self, raw: np.ndarray) -> np.ndarray:
        """Flags held ``hold`` samples after each, across batches."""
        n = len(raw)
        index = np.arange(n)
        last = np.maximum.accumulate(np.where(raw, index, -(self.hold + 1) - n))
        flagged = raw | (index - last <= self.hold) | (index < self.hold_left)
        self.hold_left = max(self.hold - (n - 1 - int(last[-1])), self.hold_left - n, 0)
        return flagged

    def _learn(self) -> None:
        """At a block's end: move the reference |B| towards its undisturbed samples and the usual levels towards
        the 90th percentile of all its samples' statistics (a disturbance of a few seconds moves them little, a
        device that turns faster than before a lot); a field flagged for longer than ``max_reject_s`` is accepted as
        the new normal and learnt again."""
        if self.flagged_run * self.period_s > self.settings.max_reject_s:
            self.reference_ut, self.levels[:], self.hold_left, self.flagged_run = 0.0, 0.0, 0, 0
        statistics = np.concatenate([part[0] for part in self.pending]) if self.pending else np.zeros((0, 1))
        norm = np.concatenate([part[1] for part in self.pending]) if self.pending else np.zeros(0)
        self.pending = []
        if len(statistics) == 0:
            return
        seconds = len(statistics) * self.period_s
        seen_s = self.samples * self.period_s
        alpha = max(-np.expm1(-seconds / self.settings.level_tau_s), min(1.0, seconds / max(seen_s, seconds)))
        if self.reference_ut == 0.0 and norm.size:
            self.reference_ut, alpha = float(np.median(norm)), 1.0
        if norm.size:
            self.reference_ut += alpha * (float(norm.mean()) - self.reference_ut)
        for j in range(statistics.shape[1]):
            values = statistics[:, j]
            values = values[np.isfinite(values)]
            if values.size:
                self.levels[j] += alpha * (float(np.percentile(values, 90)) - self.levels[j])

    def _judge(self, field: np.ndarray, gyr: np.ndarray) -> np.ndarray:
        """Flags of samples within one block (references as at the block's start)."""
        settings = self.settings
        statistics, turned = self._statistics(field, gyr)
        floors = [floor for _, floor in settings.steps] + [settings.field_tol_pct / 100.0 * self.reference_ut]
        scale = np.column_stack([turned, np.ones(len(field))])  # steps per radian turned; |B| as it is
        limits = np.maximum(np.asarray(floors), settings.relative * self.levels * scale)
        ready = self.samples * self.period_s >= settings.learn_s and self.reference_ut > 0.0
        with np.errstate(invalid="ignore"):
            flagged = self._held((statistics > limits).any(axis=1) & ready)
        calm = ~flagged
        self.pending.append((statistics / scale, row_norm(field[calm])))
        trailing = len(flagged) if flagged.all() else int(np.argmin(flagged[::-1]))
        self.flagged_run = self.flagged_run + trailing if flagged.all() else trailing
        return flagged

    def update(self, field: np.ndarray, gyr_rads: np.ndarray) -> np.ndarray:
        """(n,) bool: the samples of this batch (field (n, 3) corrected, gyr_rads (n, 3), the same body frame) that
        are disturbed."""
        out = np.zeros(len(field), dtype=bool)
        start = 0
        while start < len(field):
            stop = min(len(field), start + self.block - self.samples % self.block)
            out[start:stop] = self._judge(field[start:stop], gyr_rads[start:stop])
            self.samples += stop - start
            if self.samples % self.block == 0:
                self._learn()
            start = stop
        return out
