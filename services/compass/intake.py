"""The compass's raw path, bounded in bytes: a thread of its own (``PayloadIntake.pump``) moves raw samples out of
Zenoh's channel at once into a queue that holds at most ``max_bytes``, and the compass loop takes them from there a
drain at a time (``take``). Every message that goes no further is counted by cause.

Why bytes and not messages: a raw message may be 40 bytes or 2.5 MB (``wire.RAW_LIMITS.payload_bytes``), so a queue
of N messages bounds nothing (65,536 messages of 4 MB are 256 GB). Here:

- a payload larger than ``max_payload`` (what a raw message may be) is dropped without being copied out of Zenoh
  (``raw:oversized``);
- a payload that would take the queue past ``max_bytes`` is dropped (``raw:queue-full``); each message counts as its
  payload plus ``ENTRY_BYTES`` (its tuple, key and bytes object), so a flood of tiny messages is bounded too;
- the pump holds Zenoh's samples only while it copies them, so Zenoh's buffers are freed as fast as they arrive and
  the channel between them stays near empty;
- what waits is kept as bytes in a few segments (``SEGMENT_BYTES``, anonymous mappings of their own), not as a
  tuple, a key and a bytes object per message: a flood's backlog of 20,000 small messages was 60,000 small Python
  objects, made while the compass made the new devices' state, whose freed pools then stayed pinned by that state; a
  segment read out is given back to the system at once.

What the compass holds for raw samples is then at most: what Zenoh holds before the pump takes it (at most the
channel's capacity times the largest message Zenoh reassembles, ``transport/link/rx/max_message_size``; in practice
what arrives while the pump waits for the GIL), plus ``max_bytes``, plus one drain being decoded (``take``'s
``max_bytes``). See docs/front-door.md, "Memory per service".

The queueing takes no zenoh type: the pump takes any channel with ``recv``/``try_recv`` and samples with ``key_expr``
and a ``payload`` that has ``len`` and ``to_bytes``.
"""

from __future__ import annotations

import collections
import logging
import mmap
import struct
import threading
import time
from collections.abc import Callable, Iterable
from typing import Protocol

from magnet import wire
from services.common import zenoh_session


class RawPayload(Protocol):
    """What the pump reads of a payload (``zenoh.ZBytes``): its size, then its bytes."""

    def __len__(self) -> int: ...

    def to_bytes(self) -> bytes: ...


class RawSample(Protocol):
    """What the pump reads of a sample (``zenoh.Sample``)."""

    @property
    def key_expr(self) -> object: ...

    @property
    def payload(self) -> RawPayload: ...


#: a channel of samples (a ``zenoh.Subscriber``'s handler)
RawChannel = zenoh_session.Channel[RawSample]


#: raw payload bytes waiting for the compass loop at most (a 1,000-device fleet at 10 batches/s of 10 samples, about
#: 450 bytes each in v 2, sends 4.5 MB/s: about 14 s of it)
DEFAULT_MAX_QUEUE_BYTES = 16 * 1024 * 1024
#: what a queued message counts beyond its payload (its header and key in a segment; the tuple, key and bytes it
#: becomes when taken): at least this, or its key and header when longer
ENTRY_BYTES = 256
#: the queue's bytes are written into segments of this size (a larger message gets one of its own size): 1 MiB holds
#: about 4,500 of a flood's messages; the last one is kept while the queue is empty, the others unmapped once read out
SEGMENT_BYTES = 1024 * 1024
#: a message in a segment: its key's length, its payload's length, then the key (UTF-8) and the payload
HEADER = struct.Struct("<II")
#: samples moved from Zenoh's channel at a time (one GIL acquisition for the lot)
PUMP_BATCH = 1024
#: after a batch under PUMP_BATCH / 8, the pump waits this long (s) for more (the channel holds 256 messages: 2 ms of
#: 100,000 messages a second)
PUMP_REST_S = 0.002


class PayloadIntake:
    """A queue of (key, payload bytes) of at most ``max_bytes`` (each message counts its ``cost``), kept in segments
    of bytes, fed by ``pump`` (its own thread) and taken by the compass loop; payloads over ``max_payload`` are never
    copied."""

    def __init__(
        self, max_bytes: int = DEFAULT_MAX_QUEUE_BYTES, max_payload: int = wire.RAW_LIMITS.payload_bytes
    ) -> None:
        if max_bytes < max_payload + ENTRY_BYTES:
            raise ValueError(
                f"the raw queue must hold at least one of the largest raw messages ({max_payload + ENTRY_BYTES} "
                f"bytes), got {max_bytes}"
            )
        self.max_bytes, self.max_payload = max_bytes, max_payload
        self._segments: collections.deque[_Segment] = collections.deque()
        self._count = 0  # messages queued now
        self.queued_bytes = 0  # what the queued messages count (``cost``), now
        self.high_water_bytes = 0  # the most queued_bytes has been
        self.raw_messages = 0  # every raw message that reached the pump
        self._dropped: dict[str, int] = {}  # cause -> count, not yet handed to the service's DropCounter
        self._lock = threading.Lock()
        self._arrived = threading.Event()  # set while messages wait (``wait``)

    def offer_many(self, samples: Iterable[RawSample]) -> None:
        """Queue what fits of these Zenoh samples (called by ``pump``; any thread). The size is read before the
        payload is copied: a refused one is never copied."""
        items: list[tuple[bytes, bytes, int]] = []
        dropped: dict[str, int] = {}
        count = 0
        with self._lock:
            room = self.max_bytes - self.queued_bytes
        for sample in samples:
            count += 1
            payload = sample.payload
            size = len(payload)
            key = str(sample.key_expr).encode()
            need = cost(len(key), size)
            cause = "oversized" if size > self.max_payload else "queue-full" if need > room else None
            if cause is not None:
                dropped[cause] = dropped.get(cause, 0) + 1
                continue
            room -= need
            items.append((key, payload.to_bytes(), need))
        with self._lock:  # only take() runs meanwhile, which frees room: what was reserved is still there
            self.raw_messages += count
            if items and not self._count:
                self._arrived.set()
            self._write(items)
            self.high_water_bytes = max(self.high_water_bytes, self.queued_bytes)
            for cause, n in dropped.items():
                self._dropped[cause] = self._dropped.get(cause, 0) + n

    def _write(self, items: list[tuple[bytes, bytes, int]]) -> None:
        """Append (key, payload, cost) messages to the last segment, or to a new one when one does not fit (under the
        lock)."""
        tail = self._segments[-1] if self._segments else None
        pack_into, header = HEADER.pack_into, HEADER.size
        for key, payload, need in items:
            key_end = header + len(key)
            size = key_end + len(payload)
            if tail is None or tail.written + size > tail.size:
                tail = _Segment(max(SEGMENT_BYTES, size))
                self._segments.append(tail)
            buffer, start = tail.buffer, tail.written
            pack_into(buffer, start, len(key), len(payload))
            buffer[start + header : start + key_end] = key
            buffer[start + key_end : start + size] = payload
            tail.written = start + size
            self.queued_bytes += need
        self._count += len(items)

    def pump(
        self,
        channel: RawChannel,
        closed: type[BaseException],
        batch: int = PUMP_BATCH,
        rest: Callable[[float], None] = time.sleep,
    ) -> None:
        """Move samples from a Zenoh channel into the queue until the channel closes (``closed`` raised: the
        subscriber was undeclared), on a thread of its own (``services.common.zenoh_session.pump``). After a small
        batch it rests ``PUMP_REST_S``: taking every message as it came made the thread wake thousands of times a
        second and took the GIL from the compass's maths."""
        zenoh_session.pump(channel, closed, self.offer_many, batch, PUMP_REST_S, rest)

    def take(self, max_messages: int, max_bytes: int) -> list[tuple[str, bytes]]:
        """The oldest queued messages as (key, payload), up to ``max_messages`` and ``max_bytes`` of payload (at
        least one when any waits, however large)."""
        out: list[tuple[str, bytes]] = []
        taken = freed = 0
        unpack_from, header = HEADER.unpack_from, HEADER.size
        with self._lock:
            segments, left = self._segments, min(self._count, max_messages)
            while left:
                head = segments[0]
                if head.read == head.written:  # read out: a later segment holds the rest
                    segments.popleft().buffer.close()
                    continue
                buffer, start = head.buffer, head.read
                key_len, payload_len = unpack_from(buffer, start)
                if out and taken + payload_len > max_bytes:
                    break
                begin = start + header + key_len
                head.read = end = begin + payload_len
                out.append((buffer[start + header : begin].decode(), buffer[begin:end]))
                taken += payload_len
                freed += cost(key_len, payload_len)
                left -= 1
            self._count -= len(out)
            self.queued_bytes -= freed
            if not self._count:
                self._arrived.clear()
                self._empty()
        return out

    def _empty(self) -> None:
        """With nothing queued, unmap every segment but the last of ``SEGMENT_BYTES``, written again from its start."""
        segments = self._segments
        while segments and (len(segments) > 1 or segments[0].size != SEGMENT_BYTES):
            segments.popleft().buffer.close()
        if segments:
            segments[0].read = segments[0].written = 0

    def wait(self, timeout_s: float) -> bool:
        """Wait until a message waits, at most ``timeout_s`` (at once when one already does); whether one does."""
        return self._arrived.wait(timeout_s)

    def hand_over_drops(self, drops: wire.DropCounter, log: logging.Logger) -> None:
        """Add the drops counted since the last call to the service's counter (``raw:<cause>``), logging the first
        of each cause; call it from the service loop (the counter is not shared with the pump's thread)."""
        with self._lock:
            dropped, self._dropped = self._dropped, {}
        for cause, n in dropped.items():
            if drops.count(f"raw:{cause}", n):
                log.warning(
                    "dropping raw messages (%s): %s; further ones only counted",
                    cause,
                    f"larger than {self.max_payload} bytes"
                    if cause == "oversized"
                    else f"the queue holds {self.max_bytes} bytes already",
                )

    def figures(self) -> dict[str, int]:
        """For status: messages that arrived, queued now, bytes queued now and at most."""
        with self._lock:
            return {
                "raw_messages": self.raw_messages,
                "queued": self._count,
                "queued_bytes": self.queued_bytes,
                "queue_high_water_bytes": self.high_water_bytes,
            }

    def __len__(self) -> int:
        return self._count


def cost(key_len: int, payload_len: int) -> int:
    """What a queued message counts against ``max_bytes``: its payload plus ``ENTRY_BYTES``, or plus its key and
    header when they are longer."""
    return payload_len + (ENTRY_BYTES if key_len <= ENTRY_BYTES - HEADER.size else HEADER.size + key_len)


class _Segment:
    """Queued messages back to back in an anonymous private mapping (its pages touched only as they are written,
    given back when it is closed): ``read`` and ``written`` are offsets into it."""

    __slots__ = ("buffer", "read", "size", "written")

    def __init__(self, size: int) -> None:
        self.buffer = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        self.size, self.read, self.written = size, 0, 0
