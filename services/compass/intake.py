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
  the channel between them stays near empty.

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
#: what a queued message costs beyond its payload: the (key, payload) tuple, the key string, the bytes header
ENTRY_BYTES = 256
#: samples moved from Zenoh's channel at a time (one GIL acquisition for the lot)
PUMP_BATCH = 1024
#: after a batch under PUMP_BATCH / 8, the pump waits this long (s) for more (the channel holds 256 messages: 2 ms of
#: 100,000 messages a second)
PUMP_REST_S = 0.002


class PayloadIntake:
    """A queue of (key, payload bytes) of at most ``max_bytes`` (payloads plus ENTRY_BYTES each), fed by ``pump``
    (its own thread) and taken by the compass loop; payloads over ``max_payload`` are never copied."""

    def __init__(
        self, max_bytes: int = DEFAULT_MAX_QUEUE_BYTES, max_payload: int = wire.RAW_LIMITS.payload_bytes
    ) -> None:
        if max_bytes < max_payload + ENTRY_BYTES:
            raise ValueError(
                f"the raw queue must hold at least one of the largest raw messages ({max_payload + ENTRY_BYTES} "
                f"bytes), got {max_bytes}"
            )
        self.max_bytes, self.max_payload = max_bytes, max_payload
        self.queue: collections.deque[tuple[str, bytes]] = collections.deque()
        self.queued_bytes = 0  # payloads + ENTRY_BYTES each, now
        self.high_water_bytes = 0  # the most queued_bytes has been
        self.raw_messages = 0  # every raw message that reached the pump
        self._dropped: dict[str, int] = {}  # cause -> count, not yet handed to the service's DropCounter
        self._lock = threading.Lock()
        self._arrived = threading.Event()  # set while messages wait (``wait``)

    def offer_many(self, samples: Iterable[RawSample]) -> None:
        """Queue what fits of these Zenoh samples (called by ``pump``; any thread). The size is read before the
        payload is copied: a refused one is never copied."""
        items: list[tuple[str, bytes]] = []
        dropped: dict[str, int] = {}
        count = 0
        with self._lock:
            room = self.max_bytes - self.queued_bytes
        for sample in samples:
            count += 1
            payload = sample.payload
            size = len(payload)
            cause = "oversized" if size > self.max_payload else "queue-full" if size + ENTRY_BYTES > room else None
            if cause is not None:
                dropped[cause] = dropped.get(cause, 0) + 1
                continue
            room -= size + ENTRY_BYTES
            items.append((str(sample.key_expr), payload.to_bytes()))
        with self._lock:  # only take() runs meanwhile, which frees room: what was reserved is still there
            self.raw_messages += count
            if items and not self.queue:
                self._arrived.set()
            self.queue.extend(items)
            self.queued_bytes += sum(len(payload) for _, payload in items) + ENTRY_BYTES * len(items)
            self.high_water_bytes = max(self.high_water_bytes, self.queued_bytes)
            for cause, n in dropped.items():
                self._dropped[cause] = self._dropped.get(cause, 0) + n

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
        """The oldest queued messages, up to ``max_messages`` and ``max_bytes`` of payload (at least one when any
        waits, however large)."""
        out: list[tuple[str, bytes]] = []
        taken = 0
        with self._lock:
            queue = self.queue
            while queue and len(out) < max_messages and (not out or taken + len(queue[0][1]) <= max_bytes):
                key, payload = queue.popleft()
                taken += len(payload)
                out.append((key, payload))
            self.queued_bytes -= taken + ENTRY_BYTES * len(out)
            if not queue:
                self._arrived.clear()
        return out

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
                "queued": len(self.queue),
                "queued_bytes": self.queued_bytes,
                "queue_high_water_bytes": self.high_water_bytes,
            }

    def __len__(self) -> int:
        return len(self.queue)
