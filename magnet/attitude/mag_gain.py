"""The magnetometer's weight in the causal filter chosen from how fast the gyroscope's heading drifts (``MagneticGain``;
docs/field-calibration.md, "The magnetic gain from the gyroscope's drift").

vqf corrects its 6D heading towards the field's through a first-order loop of time constant tauMag (9 s by default):
its magnetic offset ``delta`` follows the field's angle in the 6D Earth frame. Two errors meet there. The gyroscope's
bias about the vertical, which vqf cannot learn from the accelerometer, drifts the 6D frame at b rad/s; the loop's
lag of it is b tauMag, constant while b is, and what b leaves after the lag shrinks with a shorter tauMag. The field's
own heading errors (a walker's tilt times tan(dip), a disturbance's edges the gates let through) are averaged over
tauMag: a white error of sigma_m with a correlation time tau_c leaves about sigma_m sqrt(tau_c / (2 tauMag)). Where
the gyroscope is good (its 6D heading drifts by a few tenths of a degree over a walk), tauMag = 9 s lets the field's
errors through for nothing: the heading would be better trusting the gyroscope longer.

Both are measured on ``delta`` itself, one row a batch since the record was put in force: its slope over the last
``WINDOW_S`` (exponentially weighted) is the drift of the 6D frame against the Earth's field (-b), and its scatter
about that line, sigma_d, is the field's error passed through the loop (sigma_m sqrt(tau_c) = sigma_d sqrt(2 tauMag),
whatever tauMag is). Balancing the drift over tauMag, (|b| + sigma_b) tauMag, against the field's error averaged
over it gives

    tauMag = (sigma_d sqrt(2 tauMag_now) / (|b| + sigma_b)) ** (2/3),

held between vqf's own tauMag (never shorter: where the gyroscope drifts nothing changes) and ``MAX_TAU_S``, and
moved by at most ``STEP`` a batch. sigma_b, the slope's uncertainty, counts the rows correlated over tauMag.
Nothing changes while vqf takes its first heading (``kMagInit``) nor before ``MIN_SPAN_S`` of rows after; a new
record or a restart start it again at vqf's tauMag. sigma_b counts ``SIGMAS`` times.

The compass runs it per device (``start_gain`` at each record, from ``causal_drift.take_drift``; ``note_gain`` each
fused batch, from ``causal_drift.note_batch``; a filter restarted (its time going back) or replaced drops it), but
only where ``magnet.attitude.bias_walk`` is off: that sets tauMag from the bias's uncertainty, which also grows when
the bias moves after a long still stretch (a slope measured over a minute cannot see that in time).
Plain Python, one row a fused batch; memory: a few sums.
"""

from __future__ import annotations

import math
from typing import Any

#: the drift is measured over about this long (s: the weights' time constant)
WINDOW_S = 60.0
#: tauMag is chosen only once this many seconds of rows since the record were seen
MIN_SPAN_S = 20.0
#: the longest tauMag chosen (s)
MAX_TAU_S = 60.0
#: tauMag moves by at most this factor a batch
STEP = 1.05
#: the drift counted as its estimate plus this many of its standard deviations
SIGMAS = 1.0
#: whether the compass runs it (``start_gain``)
ENABLED = True


class MagneticGain:
    """The rule of the module docstring for one vqf filter (``filter_``, a ``vqf.VQF``: its delta read, its tauMag
    set). ``note`` once a fused batch, with the time (s) since the filter's start; ``reset`` at a new record or a
    restart."""

    def __init__(self, filter_: Any, base_tau_s: float) -> None:
        self.filter = filter_
        self.base_tau_s = float(base_tau_s)
        self.tau_s = self.base_tau_s
        self.reset()

    def reset(self) -> None:
        """From the next row again, tauMag back to vqf's own."""
        self.filter.setTauMag(self.base_tau_s)
        self.tau_s = self.base_tau_s
        self.t0: float | None = None
        self.last_t = 0.0
        self.last_delta = 0.0
        self.unwrapped = 0.0
        self.sums = [0.0] * 6  # weights, t, t^2, d, t d, d^2 (t from t0)

    def note(self, t_s: float, period_s: float) -> float:
        """One row: vqf's delta now, at ``t_s``; tauMag set anew where the rule says (returned, s)."""
        delta = float(self.filter.getDelta())
        if t_s < self.last_t:  # the filter restarted
            self.reset()
        if self.t0 is None and self.filter.state["kMagInit"] != 0.0:  # vqf takes its first heading from the field
            return self.tau_s
        if self.t0 is None:
            self.reset()
            self.t0, self.last_delta, self.unwrapped = t_s, delta, delta
        step = delta - self.last_delta
        self.unwrapped += step - 2.0 * math.pi * round(step / (2.0 * math.pi))
        self.last_delta = delta
        gap = t_s - self.last_t if self.last_t else 0.0
        self.last_t = t_s
        fade = math.exp(-max(gap, 0.0) / WINDOW_S)
        t, d = t_s - self.t0, self.unwrapped
        s = self.sums
        for i, value in enumerate((1.0, t, t * t, d, t * d, d * d)):
            s[i] = s[i] * fade + value
        if t < MIN_SPAN_S:
            return self.tau_s
        w, st, stt, sd, std, sdd = s
        sxx = stt - st * st / w
        if sxx <= 0.0:
            return self.tau_s
        slope = (std - st * sd / w) / sxx
        residual = max(sdd - sd * sd / w - slope * slope * sxx, 0.0) / max(w - 2.0, 1.0)
        rows_per_correlation = max(2.0 * self.tau_s / max(gap, period_s), 1.0)
        slope_sigma = math.sqrt(residual * rows_per_correlation / sxx)
        drift = abs(slope) + SIGMAS * slope_sigma
        field_error = math.sqrt(residual) * math.sqrt(2.0 * self.tau_s)
        wanted = MAX_TAU_S if drift <= 0.0 else (field_error / drift) ** (2.0 / 3.0)
        wanted = min(max(wanted, self.base_tau_s), MAX_TAU_S)
        tau = min(max(wanted, self.tau_s / STEP), self.tau_s * STEP)
        if tau != self.tau_s:
            self.tau_s = tau
            self.filter.setTauMag(tau)
        return tau


def start_gain(state: Any) -> None:
    """A record was put in force on the compass's device ``state`` (a ``magnet.compass.filters.DeviceFilter``, after
    its filter's ``restart_magnetometer``): its ``MagneticGain`` from now on (kept as ``state.gain``), vqf's tauMag
    back to the filter's own first; none where aided or not ``ENABLED``."""
    stop_gain(state)
    fusion = state.filter
    if ENABLED and fusion is not None and not fusion.aided:
        state.gain = MagneticGain(fusion._filter, fusion._taus[1])


def note_gain(state: Any) -> None:
    """One fused batch of the device ``state``: its gain's row (``MagneticGain.note``), where it has one; dropped
    where the filter was replaced."""
    gain, fusion = getattr(state, "gain", None), state.filter
    if gain is None or fusion is None:
        return
    if gain.filter is not fusion._filter or fusion.aided:
        state.gain = None
        return
    gain.note(fusion.samples * fusion.period_s, fusion.period_s)


def stop_gain(state: Any) -> None:
    """The device ``state``'s gain dropped (a new record comes), vqf's tauMag its own again."""
    gain = getattr(state, "gain", None)
    if gain is not None:
        gain.reset()
    state.gain = None
