"""A record that hardly changes the field (an in-service refresh) moves the causal filter's heading at once, by what
it changes in the field's heading (``shift_heading``; docs/field-calibration.md, "A refresh in the causal filter").

A new record whose correction turns the field by less than a few degrees (``magnet.compass.calibrations
.small_change``) leaves vqf running: restarting its magnetic side would cost a walker ten seconds and more of
heading. vqf's magnetic heading offset ``delta`` is a first-order loop over the field's angle about the vertical in
its 6D frame (time constant tauMag: 9 s, up to 60 s with ``magnet.attitude.mag_gain``). Left alone it reaches the
new record's field only after a few tauMag: a phone whose hard iron stepped by 3-8 uT (its screen, its speaker, a
current in its board) kept the old record's error of 3-5 deg for tens of seconds after the refresh that corrected it.

The loop is linear in its input: had the new correction been in force over the history, ``delta`` would differ by
the history's change of the field's angle, new correction against old, averaged with the loop's own weights
(exp(-age / tauMag)). That is added to ``delta`` now, and the field's reference |B| and dip (vqf's disturbance
rejection) are moved by the change of their medians, so the heading carries on as if the new record had been in
force all along; nothing else (tilt, the gyroscope's bias, tauMag) changes.

numpy; vqf's frames (body FLU, earth ENU) throughout, the history of ``magnet.attitude.causal_drift.CausalDrift``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from magnet.attitude.causal_drift import Correct, delta_moved
from magnet.frames import quaternion_to_matrix

#: rows of the history needed (one a fused batch)
MIN_ROWS = 4
#: a row whose corrected field is this close to vertical (its horizontal part under this fraction of |B|) tells no
#: angle
MIN_HORIZONTAL = 0.05
#: whether the compass shifts (``shift_heading``)
ENABLED = True


def _angles(quat: np.ndarray, field: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(angle from north clockwise (rad), |B|, dip (rad, positive down), horizontal fraction) (M,) of the field
    (M, 3) body FLU in the 6D frames of ``quat`` (M, 4), as vqf measures them."""
    earth = np.einsum("nij,nj->ni", quaternion_to_matrix(quat), field)
    norm = np.maximum(np.linalg.norm(earth, axis=1), 1e-12)
    horizontal = np.hypot(earth[:, 0], earth[:, 1]) / norm
    return np.arctan2(earth[:, 0], earth[:, 1]), norm, np.arcsin(np.clip(-earth[:, 2] / norm, -1.0, 1.0)), horizontal


def shift_heading(state: Any, old: Correct | None, new: Correct | None) -> bool:
    """The device ``state``'s (a ``magnet.compass.filters.DeviceFilter``) vqf moved from the ``old`` correction to the
    ``new`` one (module docstring). True when moved; False (nothing changed) without a correction, a filter, a
    history of ``MIN_ROWS``, or where the filter is aided (its own replay answers a new record) or takes its first
    heading."""
    drift = getattr(state, "drift", None)
    fusion = getattr(state, "filter", None)
    if not ENABLED or old is None or new is None or drift is None or fusion is None or fusion.aided:
        return False
    vqf = drift.filter
    if vqf is not fusion._filter or vqf.state["kMagInit"] != 0.0 or vqf.state["magRefNorm"] <= 0.0:
        return False  # vqf has not taken the field yet
    rows, before = drift._corrected(old)
    _, after = drift._corrected(new)
    if len(rows) < MIN_ROWS:
        return False
    angle_b, norm_b, dip_b, flat_b = _angles(rows[:, 1:5], before)
    angle_a, norm_a, dip_a, flat_a = _angles(rows[:, 1:5], after)
    told = (flat_b > MIN_HORIZONTAL) & (flat_a > MIN_HORIZONTAL)
    if int(told.sum()) < MIN_ROWS:
        return False
    tau_s = float(vqf.params["tauMag"])
    weights = np.exp(-(rows[-1, 0] - rows[told, 0]) / max(tau_s, 1e-3))
    change = np.remainder(angle_a[told] - angle_b[told] + np.pi, 2.0 * np.pi) - np.pi
    state_ = vqf.state
    shift = float(weights @ change / weights.sum())
    state_["delta"] = math.remainder(float(state_["delta"]) + shift, 2.0 * math.pi)
    ratio = float(np.median(norm_a) / np.median(norm_b))
    turn = float(np.median(dip_a) - np.median(dip_b))
    for key in ("magRefNorm", "magCandidateNorm"):
        state_[key] = float(state_[key]) * ratio
    for key in ("magRefDip", "magCandidateDip"):
        state_[key] = float(state_[key]) + turn
    vqf.state = state_
    delta_moved(state, shift)  # the bias loop's delta too: a step, not a drift
    return True
