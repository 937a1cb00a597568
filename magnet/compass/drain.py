"""One drain's samples grouped by device for the compass's filters (``Drain``, made by ``make_drain``; used by
``magnet.compass.filters.DeviceFilters.update``): the columns permuted so that each device's samples follow each
other, and per batch what a device's filter judges continuity by, as Python numbers."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from magnet.attitude import fusion


class Drain(NamedTuple):
    """One drain's samples grouped by device (``DeviceFilters.update``): every array permuted so that each device's
    samples follow each other in their original order. inputs: gyroscope, accelerometer and field (S, 3) in vqf's
    frame; usable and saturated (S,) bool; per batch (in the original order): seq, first and last time (ns), count,
    whether its times strictly increase, and where its samples start in the permuted arrays."""

    inputs: tuple[np.ndarray, np.ndarray, np.ndarray]
    aiding: tuple[np.ndarray, np.ndarray] | None  # times (S,) s and velocities (S, 3) magnetic NED, or None
    usable: np.ndarray
    saturated: np.ndarray
    unusable_before: np.ndarray  # (S + 1,) int: how many samples before each (permuted) index are not usable
    batch_saturated: list[bool]
    seqs: list[int]
    first_ns: list[int]
    last_ns: list[int]
    counts: list[int]
    increasing: list[bool]
    starts: list[int]
    spans: list[float]  # per batch: the sample periods its samples span after its first (``missed.spanned``)
    stalled: np.ndarray  # (S,) bool: the samples after a stall (``missed.spanned``)
    batch_stalled: list[bool]
    raw: np.ndarray | None = None  # with ``aiding``: the raw field (S, 3), vqf's frame, permuted (``replay``)
    raw_source: tuple[np.ndarray, np.ndarray | None] | None = None  # raw field (S, 3) as given, the permutation
    expected_ut: np.ndarray | None = None  # (S,) the |B| each sample's record corrects to, uT (``first_heading``)


def make_drain(
    order: np.ndarray | None,
    edges: np.ndarray,
    seqs: Sequence[int],
    t_ns: np.ndarray,
    vectors: tuple[np.ndarray, np.ndarray, np.ndarray],
    usable: np.ndarray,
    saturated: np.ndarray,
    spans: np.ndarray,
    stalled: np.ndarray,
) -> Drain:
    """The drain's samples in vqf's frame (unusable rows zeroed), permuted by ``order`` (None: as they are), and
    per batch what ``DeviceFilter.update`` judges continuity by, as Python numbers."""
    count = int(edges[-1])
    last = np.maximum(edges[1:] - 1, 0)
    first = np.minimum(edges[:-1], max(count - 1, 0))
    steps_bad = np.concatenate([[0], np.cumsum(np.diff(t_ns) <= 0)])
    increasing = steps_bad[last] - steps_bad[first] == 0
    starts = edges[:-1]
    saturated_before = np.concatenate([[0], np.cumsum(saturated)])
    batch_saturated = saturated_before[edges[1:]] > saturated_before[edges[:-1]]
    stalled_before = np.concatenate([[0], np.cumsum(stalled)])
    batch_stalled = stalled_before[edges[1:]] > stalled_before[edges[:-1]]
    if order is not None:
        inverse = np.empty(count, dtype=np.int64)
        inverse[order] = np.arange(count)
        starts = inverse[first]
        usable, saturated, stalled = usable[order], saturated[order], stalled[order]
        vectors = (vectors[0][order], vectors[1][order], vectors[2][order])
    every = bool(usable.all())  # (the usual case: no copy with zeros to make)
    inputs = tuple(fusion.to_vqf_frame(x if every else np.where(usable[:, None], x, 0.0)) for x in vectors)
    return Drain(
        (inputs[0], inputs[1], inputs[2]), None, usable, saturated, np.concatenate([[0], np.cumsum(~usable)]),
        batch_saturated.tolist(), [int(s) for s in seqs], t_ns[first].tolist(), t_ns[last].tolist(),
        np.diff(edges).tolist(), increasing.tolist(), starts.tolist(), spans.tolist(), stalled,
        batch_stalled.tolist(),
    )  # fmt: skip
