"""The one raw decoder, for both versions.

``decode_raw_many`` checks each message's structure in Python (``raw_header.check_header``: list lengths in v 1,
dtype, shape and byte count in v 2), turns the numbers of all of them into arrays at once (v 1 lists in one
``np.array``, v 2 bytes joined and read with ``np.frombuffer``) and checks them all in one numpy pass (``_numbers``:
finite, within physical limits); when the numbers of a group do not even form arrays, each message of the group is
converted alone by the same code, which names the culprit. ``decode_raw`` is ``decode_raw_many`` of one payload
(plus the simulator's truth), so both give the same verdict and the same cause for every payload.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from magnet.earth.location import Location
from magnet.wire.arrays import Bin, check_lengths, float_array, from_bins, integers, numbers, value_faults
from magnet.wire.codec import Payload, binary_message, detached, unpack
from magnet.wire.errors import WireError
from magnet.wire.raw import (
    TRUTH_FIELDS,
    VECTOR_FIELDS,
    RawBatch,
    RawColumns,
    batch_locations,
    message_location,
    nan_rows,
    nan_values,
)
from magnet.wire.raw_header import RAW_LIMITS, Header, check_header

#: messages unpacked and checked together at most (``decode_raw_many``): each unpacked message is held until its
#: chunk's columns are made, about 2.3 kB of Python objects for a flood's message of 2 samples, so the compass's drain
#: of 8,000 new ids held 18 MB of them at once (``magnet.wire`` test ``test_decode_chunks``; docs/front-door.md,
#: "Memory per service"): the device ids kept from such a drain then pinned that memory's pymalloc arenas after it was
#: freed. A chunk of this many costs a few numpy calls more than one pass (about 50 us), and holds about 1 MB
DECODE_CHUNK = 500


def _gather(values: list[Any], name: str, times: bool) -> np.ndarray:
    """The rows of ``values`` (per message, in order: a list of rows (v 1) or a ``Bin`` (v 2)) as one array: t_ns
    (S,) int64 or (S, 3) float64. Lists in one ``np.array`` per run of v 1 messages, bytes in one ``np.frombuffer``
    per run of v 2 messages. WireError when the lists do not form such an array."""
    if len({type(value) for value in values}) == 1:  # one version throughout (the usual case): one run
        if type(values[0]) is Bin:
            return from_bins(values, () if times else (3,), "i8" if times else "f8")
        rows = [row for value in values for row in value]
        return integers(rows, "t_ns") if times else numbers(rows, name, (3,))
    parts: list[np.ndarray] = []
    start = 0
    for i in range(1, len(values) + 1):
        if i < len(values) and type(values[i]) is type(values[start]):
            continue
        run = values[start:i]
        if type(run[0]) is Bin:
            parts.append(from_bins(run, () if times else (3,), "i8" if times else "f8"))
        else:
            rows = [row for value in run for row in value]
            parts.append(integers(rows, "t_ns") if times else numbers(rows, name, (3,)))
        start = i
    return parts[0] if len(parts) == 1 else np.concatenate(parts)


def _arrays(headers: Sequence[Header]) -> tuple[np.ndarray, list[np.ndarray]]:
    """t_ns (S,) and one (S, 3) array per VECTOR_FIELDS entry (NaN rows where absent); WireError when the numbers
    of these messages do not form such arrays."""
    counts = [h.n for h in headers]
    total = sum(counts)
    vectors = []
    for k, (name, _, _) in enumerate(VECTOR_FIELDS):
        mask = [h.present[k] for h in headers]
        values = [h.arrays[k + 1] for h in headers if h.present[k]]
        if all(mask):
            vectors.append(_gather(values, name, False))
            continue
        arr = nan_rows(total)
        if values:
            arr[np.repeat(mask, counts)] = _gather(values, name, False)
        vectors.append(arr)
    return _gather([h.arrays[0] for h in headers], "t_ns", True), vectors


def _sample_faults(
    t_ns: np.ndarray, vectors: list[np.ndarray], starts: np.ndarray
) -> list[tuple[np.ndarray, str, str]]:
    """Per-sample faults (S,) bool, most fundamental first, with their cause and message. ``starts`` (B,): where
    each message's samples begin (time is judged within a message only)."""
    backwards = np.zeros(t_ns.shape, dtype=bool)
    backwards[1:] = t_ns[1:] < t_ns[:-1]
    backwards[starts] = False
    per_field = [
        value_faults(arr, name, limit, absent_rows=True) for arr, (name, limit, _) in zip(vectors, VECTOR_FIELDS)
    ]
    return [
        (t_ns < 0, "out-of-range", "t_ns holds negative times"),
        (backwards, "time-backwards", "t_ns decreases within the batch"),
        *(faults[0] for faults in per_field),  # every field's non-finite values first, then magnitudes
        *(faults[1] for faults in per_field),
    ]


def _numbers(headers: Sequence[Header]) -> tuple[RawColumns, list[WireError | None]]:
    """All messages as columns and, per message, the WireError its numbers earn (None when good); WireError when
    the numbers of these messages do not even form arrays. The same checks for both versions."""
    t_ns, vectors = _arrays(headers)
    counts = np.array([h.n for h in headers], dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    verdicts: list[WireError | None] = [None] * len(headers)
    for bad, cause, text in _sample_faults(t_ns, vectors, starts):
        if bad.any():
            for i in np.flatnonzero(np.logical_or.reduceat(bad, starts)).tolist():
                verdicts[i] = verdicts[i] or WireError(cause, text)
    mag_ut, acc_ms2, gyr_rads, vel_ned_ms = vectors
    current_a, throttle = (_scalar_column(headers, k) for k in range(2))
    columns = RawColumns(
        [h.device for h in headers],
        [h.seq for h in headers],
        counts,
        t_ns,
        mag_ut,
        acc_ms2,
        gyr_rads,
        [h.sensor for h in headers],
        None,
        vel_ned_ms,
        current_a,
        throttle,
        [h.vehicle for h in headers] if any(h.vehicle for h in headers) else None,
        [h.hardware_id for h in headers] if any(h.hardware_id for h in headers) else None,
    )
    return columns, verdicts


def _scalar_column(headers: Sequence[Header], k: int) -> np.ndarray | None:
    """(S,) the k-th SCALAR_FIELDS entry of every message (checked in the header), NaN where absent; None when no
    message carries it."""
    if all(h.scalars[k] is None for h in headers):
        return None
    return np.concatenate([nan_values(h.n) if h.scalars[k] is None else h.scalars[k] for h in headers])


def _alone(header: Header) -> tuple[list[RawBatch], WireError | None]:
    """``_numbers`` of one message: its batch (or none) and its verdict."""
    try:
        columns, (verdict,) = _numbers([header])
    except WireError as exc:
        return [], detached(exc)
    return ([] if verdict else columns.batches()), verdict


def decode_messages(
    messages: Sequence[Mapping[str, Any]], sizes: Sequence[int] | None = None
) -> tuple[RawColumns, list[tuple[int, WireError]]]:
    """The raw decoder: unpacked messages (and their payloads' sizes in bytes, when known) -> (good batches as
    columns, in order; (index, WireError) per refusal, sorted by index)."""
    errors: list[tuple[int, WireError]] = []
    kept: list[int] = []
    headers: list[Header] = []
    locations: list[Location | None] = []
    for index, message in enumerate(messages):
        try:
            header = check_header(message, None if sizes is None else sizes[index])
            location = message_location(message)
        except WireError as exc:
            errors.append((index, detached(exc)))
            continue
        headers.append(header)
        locations.append(location)
        kept.append(index)
    if not headers:
        return RawColumns.from_batches([]), errors
    try:
        columns, verdicts = _numbers(headers)
        columns = dataclasses.replace(columns, locations=batch_locations(locations))
        if any(v is not None for v in verdicts):  # every batch good (the usual case): no copy
            columns = columns.select(np.array([v is None for v in verdicts], dtype=bool))
    except WireError:  # rare: some message's numbers are not arrays; judge each alone to name it
        alone = [_alone(h) for h in headers]
        verdicts = [verdict for _, verdict in alone]
        columns = RawColumns.from_batches(
            [
                dataclasses.replace(batch, location=location)
                for (batches, _), location in zip(alone, locations)
                for batch in batches
            ]
        )
    errors += [(index, v) for index, v in zip(kept, verdicts) if v is not None]
    return columns, sorted(errors, key=lambda e: e[0])


def decode_raw_many(payloads: Sequence[Payload]) -> tuple[RawColumns, list[tuple[int, WireError]]]:
    """Decode many raw payloads at once (the hot path of a busy consumer), ``DECODE_CHUNK`` at a time.

    Returns the good batches as columns, in input order, and (index, WireError) for each payload refused, sorted by
    index. ``truth`` is not decoded."""
    parts: list[RawColumns] = []
    errors: list[tuple[int, WireError]] = []
    for start in range(0, len(payloads), DECODE_CHUNK):
        columns, refused = _decode_chunk(payloads[start : start + DECODE_CHUNK])
        parts.append(columns)
        errors += [(start + index, exc) for index, exc in refused]
    return RawColumns.joined(parts), errors


def _decode_chunk(payloads: Sequence[Payload]) -> tuple[RawColumns, list[tuple[int, WireError]]]:
    """``decode_raw_many`` of one chunk: every payload unpacked, then their columns made together."""
    messages: list[Mapping[str, Any]] = []
    sizes: list[int] = []
    where: list[int] = []
    errors: list[tuple[int, WireError]] = []
    for index, payload in enumerate(payloads):
        try:
            messages.append(unpack(payload, RAW_LIMITS))
            sizes.append(len(payload))
            where.append(index)
        except WireError as exc:
            errors.append((index, detached(exc)))
    columns, refused = decode_messages(messages, sizes)
    errors += [(where[i], exc) for i, exc in refused]
    return columns, sorted(errors, key=lambda e: e[0])


def decode_raw(payload: Payload, *, with_truth: bool = True) -> RawBatch:
    """RawBatch from a payload; WireError (with ``cause``) for anything malformed or physically impossible.

    The verdict is ``decode_raw_many``'s; ``with_truth=False`` skips the simulator's truth (faster, for consumers
    that do not use it)."""
    message = unpack(payload, RAW_LIMITS)
    columns, errors = decode_messages([message], [len(payload)])
    if errors:
        exc = errors[0][1]
        del message, columns, errors
        try:
            raise exc
        finally:  # no reference cycle exc -> traceback -> this frame -> exc
            del exc
    batch = columns.batches()[0]
    if not with_truth or message.get("truth") is None:
        return batch
    return dataclasses.replace(batch, truth=_truth(message["truth"], len(batch), binary_message(message)))


def _truth(raw_truth: Any, n: int, binary: bool) -> dict[str, np.ndarray]:
    if not isinstance(raw_truth, dict):
        raise WireError("bad-field", "truth must be a map")
    truth = {name: float_array(raw_truth.get(name), f"truth.{name}", (), 1e4, binary) for name in TRUTH_FIELDS}
    check_lengths(n, truth)
    return truth
