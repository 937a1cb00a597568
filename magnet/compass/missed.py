"""Samples missing within a batch (``spanned``; docs/field-calibration.md, "Phone realities"): the gyroscope's sample
after them taken over the time since the one before, and the batch's period from its whole steps.

The compass's filter runs at one period per device (``filters.DeviceFilter``): each sample's rate turns the attitude
by rate x period, and the period is a batch's mean step. A phone's stream drops samples (a busy sensor hub, a full
FIFO, a logger): each one dropped lost its rotation (a swinging hand turns 2-6 deg in 20 ms), and it lengthened its
batch's mean step, so that the filter ran a few % slow or started again. The rate after k missing samples is the
best estimate of the rate over them, so it is fed k + 1 times as large, and a batch's period is its time over its
whole steps. A step is whole periods of the batch's shortest step, rounded: time stamps' jitter moves a step by a
fraction, and a stream without gaps is fed as it was, to the bit. Where a step looks longer, the period is the
batch's median step instead: a flight log's time stamps come in pairs 0.75 ms apart at 10 ms (PX4's sample log), and
against its shortest step every step looked like 14 periods.

At most ``MOST_MISSING`` in a row are made up for: over a longer stall (a busy phone: 0.2-0.5 s) the rotation is
unknown. Its steps still count in the batch's period: counted only up to the limit, a stall of 20 samples in a batch
of 25 made the period 1.6 times too long, so that the filter restarted by accident, or ran the batch's other samples
too fast. After a stall (``stalled``) the attitude has lost the stall's rotation, tilt and heading alike, and one of
two things is done (``start_again``):

- the filter starts again, as after a gap between batches: its tilt from the accelerometer at once, its heading from
  the field over tauMag. Right where the accelerometer is near gravity: a phone in a pocket, held to text or to phone;
- where the device swings (an arm's, a runner's: the turn gate's swing, ``magnet.attitude.turn_gate``), an
  accelerometer sample is gravity plus the swing's centripetal acceleration w^2 r (10 m/s^2 and more at the ends of
  the swing), and a tilt taken from it is off by tens of degrees for tauAcc: the filter goes on, the heading it
  carries off by the stall's rotation, and the heading gate forgets its usual level (``heading_unknown``): the
  field's disagreement is the stall's, not a disturbance, and it pulls the heading back at vqf's pace instead of
  being left out.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from magnet.calibration.sample_runs import MOST_MISSING  # missing samples in a row made up for at most (the runs' too)

if TYPE_CHECKING:
    from magnet.attitude.fusion import Fusion


def spanned(gyr_rads: np.ndarray, t_ns: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(the gyroscope's rates (S, 3), each sample after k missing ones multiplied by k + 1, at most MOST_MISSING + 1
    (the same array where none is missing); per batch between ``edges`` (B + 1,), the periods its samples span after
    its first (B,), count - 1 where none is missing; the samples after a stall, more than MOST_MISSING missing (S,)
    bool). A step is k + 1 periods when it is k + 1 times the batch's period, rounded: its shortest step, or where a
    step is longer than 1.5 of those, its median step (``_typical``)."""
    sizes = np.diff(edges)
    spans = np.maximum(sizes - 1, 0).astype(float)
    stalled = np.zeros(len(t_ns), dtype=bool)
    if len(t_ns) < 2:
        return gyr_rads, spans, stalled
    steps = np.diff(np.asarray(t_ns, dtype=np.int64), prepend=np.int64(t_ns[0])).astype(float)
    nonempty = sizes > 0
    first = np.asarray(edges[:-1], dtype=np.int64)[nonempty]
    steps[first] = np.inf  # a batch's first sample: no step within the batch
    positive = np.where(steps > 0.0, steps, np.inf)
    shortest = np.full(len(sizes), np.inf)
    shortest[nonempty] = np.minimum.reduceat(positive, first)  # over each batch's own samples
    ratio = steps / np.repeat(shortest, sizes)
    periods = np.where(np.isfinite(ratio), np.maximum(np.rint(ratio), 1.0), 1.0)
    if not (periods > 1.0).any():
        return gyr_rads, spans, stalled
    ratio = steps / np.repeat(_typical(positive, edges, first, shortest, periods), sizes)
    periods = np.where(np.isfinite(ratio), np.maximum(np.rint(ratio), 1.0), 1.0)
    extra = np.zeros(len(sizes))
    extra[nonempty] = np.add.reduceat(periods - 1.0, first)
    stalled = periods > MOST_MISSING + 1.0
    return gyr_rads * np.minimum(periods, MOST_MISSING + 1.0)[:, None], spans + extra, stalled


def _typical(
    positive: np.ndarray, edges: np.ndarray, first: np.ndarray, shortest: np.ndarray, periods: np.ndarray
) -> np.ndarray:
    """(B,) ns: each batch's period: its shortest step (positive (S,) ns, inf where none), or its median one where a
    step looked like more than one (periods (S,) > 1 by the shortest): time stamps that come in pairs a fraction of a
    period apart (a flight log's, 0.75 ms apart at 10 ms) made the shortest step a fraction of the period, and every
    step look like a gap (B batches between ``edges`` (B + 1,); ``first`` the nonempty ones' first samples)."""
    typical, longer = shortest.copy(), np.zeros(len(shortest), dtype=bool)
    longer[np.diff(edges) > 0] = np.logical_or.reduceat(periods > 1.0, first)  # first: the nonempty batches' starts
    for b in np.flatnonzero(longer).tolist():
        steps = positive[edges[b] : edges[b + 1]]
        typical[b] = float(np.median(steps[np.isfinite(steps)]))
    return typical


def start_again(fusion: Fusion) -> bool:
    """Whether ``fusion`` starts again after a stall: unless its turn gate finds the device in a swing (an arm's, a
    runner's: ``magnet.attitude.turn_gate``, its body rates' spread of 2.2-8 rad/s repeating at a stride's lag)."""
    gate = fusion.turn_gate
    return gate is None or not gate.in_swing


def heading_unknown(fusion: Fusion | None) -> None:
    """After a stall: the heading gate of ``fusion`` (``magnet.attitude.heading_gate``, where it has one) forgets
    the usual disagreement of the field with the heading."""
    gate = None if fusion is None else fusion.turn_gate
    if gate is not None and gate.heading is not None:
        gate.heading.forget_level()
