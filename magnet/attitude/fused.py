"""What ``magnet.attitude.fusion`` gives: the fused attitude of N samples in the project's frames (``Fused``), made
from vqf's outputs (body FLU -> ENU) once, at the boundary (``magnet.frames.ned_enu_attitude``)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from magnet.frames import ned_enu_attitude, quaternion_to_euler


@dataclasses.dataclass(frozen=True)
class Fused:
    """Fused attitude per sample (N samples). quat_wxyz: (N, 4) body -> NED (magnetic north), w >= 0. heading_deg (N,)
    magnetic heading of body x in [0, 360); pitch_deg, roll_deg (N,). mag_disturbed (N,) bool: vqf's magnetic
    disturbance detection (|B| or dip away from its reference; the field is then not used for heading). rest (N,)
    bool: vqf's rest detection. With no magnetometer the heading is the gyroscope's, relative to where the filter
    started, and mag_disturbed is all False."""

    quat_wxyz: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    mag_disturbed: np.ndarray
    rest: np.ndarray

    @classmethod
    def from_vqf(cls, out: Mapping[str, Any], with_mag: bool) -> Fused:
        quat = ned_enu_attitude(np.asarray(out["quat9D" if with_mag else "quat6D"], dtype=float).reshape(-1, 4))
        heading, pitch, roll = quaternion_to_euler(quat)
        count = len(quat)
        disturbed = np.asarray(out["magDistDetected"], dtype=bool).reshape(count) if with_mag else np.zeros(count, bool)
        rest = np.asarray(out["restDetected"], dtype=bool).reshape(count)
        return cls(quat, heading, pitch, roll, disturbed, rest)

    @classmethod
    def empty(cls) -> Fused:
        """No samples."""
        zeros = np.zeros(0)
        return cls(np.zeros((0, 4)), zeros, zeros, zeros, np.zeros(0, bool), np.zeros(0, bool))
