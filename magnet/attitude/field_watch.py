"""A watch over the field (``FieldWatch``): which samples a passing disturbance (a steel door, a parked car, a magnet)
changes, causal and batch by batch, so that the attitude filter leaves them out and holds its heading on the
gyroscope meanwhile (``magnet.attitude.fusion.Fusion``, on by default; docs/compass.md, "Disturbances"). Its
per-sample loop is compiled (``magnet._kernels.watch_update``, docs/cost.md).

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

from magnet.compiled import kernels as _kernels


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


#: the one definition of a disturbed field's steps and strength, shared by the watch (the compass, ``magnet heading``)
#: and ``magnet.quality.disturbance`` (whole logs, the fits): step windows with their floors ((window_s, floor_ut),
#: ...) between means over SMOOTH_S; |B| beyond FIELD_TOL_PCT % of its reference; a step's level per radian turned
#: within its window, plus TURN_FLOOR_RAD
STEPS: tuple[tuple[float, float], ...] = ((0.25, 2.5), (2.0, 3.5))
SMOOTH_S = 0.1
FIELD_TOL_PCT = 8.0
TURN_FLOOR_RAD = 0.25


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

    steps: tuple[tuple[float, float], ...] = STEPS
    smooth_s: float = SMOOTH_S
    relative: float = 4.0
    field_tol_pct: float = FIELD_TOL_PCT
    learn_s: float = 5.0
    level_tau_s: float = 20.0
    hold_s: float = 0.5
    max_reject_s: float = 10.0
    turn_floor_rad: float = TURN_FLOOR_RAD


class FieldWatch:
    """``field_disturbance``'s steps and magnitude, causal and batch by batch, for one device's filter: ``update``
    takes the corrected field and the gyroscope (N, 3) (any one body frame; rad/s) and says which samples are
    disturbed. Its references are its own (learnt from the samples, as vqf learns its own: a calibration's leftover
    error raises the usual levels, and with them what counts as unusual). The samples are judged in blocks of
    ``BLOCK_S`` counted from the start, the references moving at each block's end, so the flags are the same however
    the samples are batched. Each sample: the attitude integrated from the start (q_k = q_{k-1} exp(w_k dt)), the
    field in its frame (``to_frame``) and its mean over ``smooth_s``; each step window's change of that mean and the
    gyroscope's path over the window (+ ``turn_floor_rad``); | |B| - reference |; flagged where a statistic is over
    max(floor, relative x usual level (x path for steps)) once ``learn_s`` has passed, held ``hold_s`` after. At a
    block's end the reference |B| moves towards the block's calm samples' mean (their median first) and each usual
    level towards the 90th percentile of the block's statistics (per radian), with the weight max(1 - exp(-block /
    level_tau_s), block / seen). The loop is compiled (``magnet._kernels.watch_update``; docs/cost.md). State: the
    integrated attitude, the last ``max(windows) + smooth`` samples, the references and levels, the hold; bounded."""

    BLOCK_S = 0.5
    #: ``state``'s entries (as magnet/_kernels.c names them): attitude wxyz, radians turned, samples seen, reference
    #: |B| (uT), hold left, flagged run, the block's pending and calm counts, the running sum of the last ``smooth``
    #: samples' field in the integrated frame (x, y, z; summed afresh every ring's length, so its rounding stays small).
    STATE = (
        "qw", "qx", "qy", "qz", "turned", "samples", "reference_ut", "hold_left", "flagged_run", "pending", "calm",
        "sum_x", "sum_y", "sum_z",
    )  # fmt: skip

    def __init__(self, period_s: float, settings: WatchSettings = WatchSettings()) -> None:
        self.period_s, self.settings = float(period_s), settings
        self.widths = [max(1, round(window / self.period_s)) for window, _ in settings.steps]
        self.smooth = max(1, round(settings.smooth_s / self.period_s))
        self.hold = round(settings.hold_s / self.period_s)
        self.block = max(1, round(self.BLOCK_S / self.period_s))
        self._widths = np.asarray(self.widths, dtype=float)
        self._floors = np.asarray([floor for _, floor in settings.steps], dtype=float)
        self.reset()

    def reset(self) -> None:
        """Forget everything (the filter restarted)."""
        self.state = np.zeros(len(self.STATE))
        self.state[0] = 1.0
        self.levels = np.zeros(len(self.widths) + 1)  # usual step statistics (per radian), then usual | |B| - ref |
        self.ring = np.zeros((max(self.widths) + self.smooth, 7))  # field in the integrated frame, its mean, turned
        self.pending = np.zeros((self.block, len(self.widths) + 1))  # this block's statistics so far
        self.calm = np.zeros(self.block)  # this block's calm samples' |B|
        s = self.settings
        #: the watch's tail of ``watch_update``'s arguments (from widths on), for ``magnet._kernels.fuse_rows``
        self.kernel_args = (
            self._widths, self._floors, self.state, self.levels, self.ring, self.pending, self.calm, self.period_s,
            self.smooth, self.hold, self.block, s.relative, s.field_tol_pct, s.learn_s, s.level_tau_s,
            s.max_reject_s, s.turn_floor_rad,
        )  # fmt: skip

    @property
    def reference_ut(self) -> float:
        """The running reference |B| (uT; 0 until learnt)."""
        return float(self.state[self.STATE.index("reference_ut")])

    def update(self, field: np.ndarray, gyr_rads: np.ndarray) -> np.ndarray:
        """(n,) bool: the samples of this batch (field (n, 3) corrected, gyr_rads (n, 3), the same body frame) that
        are disturbed."""
        field = np.asarray(field, dtype=float)
        gyr = np.asarray(gyr_rads, dtype=float)
        if field.ndim != 2 or field.shape[1:] != (3,) or gyr.shape != field.shape:
            raise ValueError(f"field and gyr_rads must both be (n, 3); got {field.shape} and {gyr.shape}")
        out = np.zeros(len(field), dtype=bool)
        s = self.settings
        _kernels.watch_update(
            field, gyr, out, self.state, self.levels, self.ring, self.pending, self.calm, self._widths,
            self._floors, self.period_s, self.smooth, self.hold, self.block, s.relative, s.field_tol_pct,
            s.learn_s, s.level_tau_s, s.max_reject_s, s.turn_floor_rad,
        )  # fmt: skip
        return out
