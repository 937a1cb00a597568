"""Samples missing within a batch (``spanned``; docs/field-calibration.md, "Phone realities"): the gyroscope's sample
after them taken over the time since the one before, and the batch's period from its whole steps.

The compass's filter runs at one period per device (``filters.DeviceFilter``): each sample's rate turns the attitude
by rate x period, and the period is a batch's mean step. A phone's stream drops samples (a busy sensor hub, a full
FIFO, a logger): each one dropped lost its rotation (a swinging hand turns 2-6 deg in 20 ms), and it lengthened its
batch's mean step, so that the filter ran a few % slow or started again. The rate after k missing samples is the
best estimate of the rate over them, so it is fed k + 1 times as large, and a batch's period is its time over its
whole steps. A step is whole periods of the batch's shortest step, rounded: time stamps' jitter moves a step by a
fraction, and a stream without gaps is fed as it was, to the bit. At most ``MOST_MISSING`` in a row: over a longer
stall the rotation is unknown.
"""

from __future__ import annotations

import numpy as np

#: missing samples in a row made up for at most
MOST_MISSING = 3


def spanned(gyr_rads: np.ndarray, t_ns: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the gyroscope's rates (S, 3), each sample after k missing ones multiplied by k + 1 (the same array where none
    is missing); per batch between ``edges`` (B + 1,), the periods its samples span after its first (B,), count - 1
    where none is missing). A step is k + 1 periods when it is k + 1 times the batch's shortest step, rounded."""
    sizes = np.diff(edges)
    spans = np.maximum(sizes - 1, 0).astype(float)
    if len(t_ns) < 2:
        return gyr_rads, spans
    steps = np.diff(np.asarray(t_ns, dtype=np.int64), prepend=np.int64(t_ns[0])).astype(float)
    nonempty = sizes > 0
    first = np.asarray(edges[:-1], dtype=np.int64)[nonempty]
    steps[first] = np.inf  # a batch's first sample: no step within the batch
    positive = np.where(steps > 0.0, steps, np.inf)
    shortest = np.full(len(sizes), np.inf)
    shortest[nonempty] = np.minimum.reduceat(positive, first)  # over each batch's own samples
    ratio = steps / np.repeat(shortest, sizes)
    whole = np.where(np.isfinite(ratio), np.clip(np.rint(ratio), 1.0, MOST_MISSING + 1.0), 1.0)
    if not (whole > 1.0).any():
        return gyr_rads, spans
    extra = np.zeros(len(sizes))
    extra[nonempty] = np.add.reduceat(whole - 1.0, first)
    return gyr_rads * whole[:, None], spans + extra
