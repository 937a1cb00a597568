"""A travelling vehicle's turns lean its unaided tilt: the field ladder's vertical evidence of a planar vehicle that
turns under way takes its mean down direction (docs/field-calibration.md, "A boat's turns"). Pure numpy."""

from __future__ import annotations

import dataclasses

import numpy as np

from magnet.calibration.rungs import Evidence, mean_down

#: a travelling planar device's turns lean its unaided tilt when their centripetal acceleration (the rate about the
#: vertical times the speed over the ground), RMS over the samples, reaches this (m/s^2; 0.2 leans it by 1.2 deg)
CENTRIPETAL_MS2 = 0.2


def centripetal_ms2(ev: Evidence, gyr_rads: np.ndarray | None, vel_ned_ms: np.ndarray | None) -> float:
    """RMS (m/s^2) of the centripetal acceleration of a vehicle's turns, |rate about its mean vertical| x its speed
    over the ground: gyr_rads (N, 3) rad/s, vel_ned_ms (N, 3) m/s (NaN rows before a fix, left out); 0 without
    either. Needs no heading: a vehicle turning at 0.2 rad/s at 4 m/s reads 0.8 m/s^2 across its track."""
    if gyr_rads is None or vel_ned_ms is None:
        return 0.0
    vel = np.asarray(vel_ned_ms, dtype=float)
    known = np.all(np.isfinite(vel), axis=1)
    if not known.any():
        return 0.0
    rate = np.asarray(gyr_rads, dtype=float)[known] @ mean_down(ev.down)
    speed = np.linalg.norm(vel[known, :2], axis=1)
    return float(np.sqrt(np.mean((rate * speed) ** 2)))


def level_in_turns(ev: Evidence, gyr_rads: np.ndarray | None, vel_ned_ms: np.ndarray | None) -> Evidence:
    """The evidence of a planar device whose turns' centripetal acceleration (``centripetal_ms2``) reaches
    CENTRIPETAL_MS2, its down direction (N, 3) replaced by its mean (``mean_down``); else ``ev`` as it is.

    Why: without a calibration in force the tilt is the gyroscope + accelerometer filter's, unaided, and in a turn
    held for tens of seconds (a boat's circle) it leans towards the turn's centre by atan(a / g). The vertical block
    (d . b = v) then reads part of the horizontal field as vertical, the more the longer the turn, and pulls the
    horizontal offset: on the simulated boat (tuning seeds 1 and 10, the offset rung on the first 43 s) the field's
    heading error (true attitude) was 3.3 and 7.5 deg with the filter's down, 1.3 and 1.7 with the true down and
    1.3 and 1.3 with the mean. A vehicle that only yaws stays within its waves' few degrees of its mean down, whose
    errors come and go with the waves, not with the turns."""
    if ev.down is None or centripetal_ms2(ev, gyr_rads, vel_ned_ms) < CENTRIPETAL_MS2:
        return ev
    level = dataclasses.replace(ev, down=np.tile(mean_down(ev.down), (len(ev.mag), 1)))
    level.__dict__["basis"] = ev.basis  # the same plane
    return level
