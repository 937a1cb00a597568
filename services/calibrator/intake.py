"""The calibrator's sample path, bounded: raw messages queue between Zenoh and the service loop, new device ids are
admitted at a bounded rate, and every message that goes no further is counted by cause.

- ``RawIntake``: a thread of its own (``pump``) moves raw messages from Zenoh's channel to a queue of at most
  ``max_queue`` messages and ``max_bytes`` bytes (each message counted as its payload plus ``ENTRY_BYTES``), counting
  each; beyond, a message is dropped and counted (``raw:queue-full``). A payload larger than any raw message may be
  is dropped without being copied out of Zenoh (``raw:oversized``). The thread
  keeps Zenoh's channel near empty, so Zenoh is not held up (nothing is lost unseen in the transport, queries are
  not stuck behind samples), and the service loop takes the queue a slice at a time, between which it answers
  queries (status, ``@fleet``, calibrations): a flood delays samples, never answers.
- ``Enrolment``: a token bucket (``rate_per_s``, ``burst``) for device ids the calibrator does not know yet; a
  message of a new id beyond it is dropped before decoding and counted (``raw:enrol-rate``). Known devices always
  pass. With ``--max-devices`` this bounds both the work and the memory a flood of ids can take.

Every raw message that reaches the callback is in ``raw_messages``; once the queue is empty, ``raw_messages`` =
decoded batches (``received_batches``) + the drops of cause ``raw:*`` (status ``dropped``).
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

import zenoh
from zenoh.handlers import Handler

from magnet import wire
from services.common import zenoh_session

#: raw messages waiting for the service loop at most (about 10 s of a 1,000-device fleet at 10 batches/s)
DEFAULT_MAX_QUEUE = 100_000
#: new device ids admitted per second, and at once after a quiet spell (a fleet starting together)
DEFAULT_ENROL_RATE = 200.0
DEFAULT_ENROL_BURST = 2_000
#: raw payload bytes waiting for the service loop at most (a burst of 2.5 MB messages is a dozen of them, not 100,000)
DEFAULT_MAX_QUEUE_BYTES = 32 * 1024 * 1024
#: what a queued message costs beyond its payload: the (key, payload) tuple, the key string, the bytes header
ENTRY_BYTES = 256
#: samples moved from Zenoh's channel to the queue at a time
PUMP_BATCH = 4096


class RawIntake:
    """A bounded queue of (key, payload) fed by Zenoh's callback thread and drained by the service loop;
    ``max_queue`` >= 1 messages (``--max-queue``, checked with the settings) and ``max_bytes``."""

    def __init__(
        self,
        max_queue: int = DEFAULT_MAX_QUEUE,
        max_bytes: int = DEFAULT_MAX_QUEUE_BYTES,
        max_payload: int = wire.RAW_LIMITS.payload_bytes,
    ) -> None:
        self.max_queue, self.max_bytes, self.max_payload = max_queue, max_bytes, max_payload
        self.queue: collections.deque[tuple[str, bytes]] = collections.deque()
        self.queued_bytes = 0  # payloads + ENTRY_BYTES each, now
        self.raw_messages = 0  # every raw message that arrived
        self.queue_full = 0  # of which dropped because the queue was full
        self.oversized = 0  # of which dropped, uncopied, for being larger than any raw message
        self.high_water = 0  # longest the queue has been
        self._lock = threading.Lock()

    def offer(self, key_expr: str, payload: bytes) -> bool:
        """Queue one message (from Zenoh's thread); False (counted) when the queue is full."""
        return self.offer_many([(key_expr, payload)]) == 1

    def offer_many(self, items: list[tuple[str, bytes]]) -> int:
        """Queue what fits of these messages, in order, under one lock; the others are counted. How many were
        queued."""
        with self._lock:
            self.raw_messages += len(items)
            room_messages, room_bytes = self.max_queue - len(self.queue), self.max_bytes - self.queued_bytes
            queued = 0
            for item in items:
                size = len(item[1]) + ENTRY_BYTES
                if queued >= room_messages or size > room_bytes:
                    self.queue_full += 1
                    continue
                self.queue.append(item)
                room_bytes -= size
                self.queued_bytes += size
                queued += 1
            self.high_water = max(self.high_water, len(self.queue))
            return queued

    def pump(
        self,
        channel: Handler[zenoh.Sample],
        payload_of: Callable[[zenoh.Sample], bytes],
        closed: type[BaseException],
        batch: int = PUMP_BATCH,
    ) -> None:
        """Move samples from a Zenoh channel into the queue until the channel closes (``closed`` raised: the
        subscriber was undeclared), on a thread of its own (``services.common.zenoh_session.pump``), so that Zenoh's
        threads never wait for Python (queries keep flowing during a flood)."""
        zenoh_session.pump(channel, closed, lambda samples: self._offer_samples(samples, payload_of), batch)

    def _offer_samples(self, samples: list[zenoh.Sample], payload_of: Callable[[zenoh.Sample], bytes]) -> None:
        """Queue what fits of these samples; one larger than any raw message is counted and never copied."""
        fit = [sample for sample in samples if len(sample.payload) <= self.max_payload]  # the size, uncopied
        with self._lock:
            self.oversized += len(samples) - len(fit)
            self.raw_messages += len(samples) - len(fit)
        self.offer_many([(str(sample.key_expr), payload_of(sample)) for sample in fit])

    def take(self, limit: int) -> list[tuple[str, bytes]]:
        """Up to ``limit`` queued messages, oldest first."""
        out: list[tuple[str, bytes]] = []
        with self._lock:
            queue = self.queue
            while queue and len(out) < limit:
                out.append(queue.popleft())
            self.queued_bytes -= sum(len(payload) for _, payload in out) + ENTRY_BYTES * len(out)
        return out

    def __len__(self) -> int:
        return len(self.queue)


class Enrolment:
    """A token bucket for new device ids: ``rate_per_s`` a second (> 0: ``--enrol-rate``, checked with the settings),
    at most ``burst`` (>= 1) at once. ``clock`` (s)."""

    def __init__(
        self,
        rate_per_s: float = DEFAULT_ENROL_RATE,
        burst: int = DEFAULT_ENROL_BURST,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.rate_per_s, self.burst, self.clock = float(rate_per_s), burst, clock
        self.tokens = float(burst)
        self.last = clock()
        self.admitted = self.refused = 0

    def admit(self) -> bool:
        """Whether one more new device may be enrolled now (counted either way)."""
        now = self.clock()
        self.tokens = min(float(self.burst), self.tokens + (now - self.last) * self.rate_per_s)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            self.admitted += 1
            return True
        self.refused += 1
        return False


def new_device(key_expr: str, prefix: str, known: Callable[[str], bool]) -> bool:
    """Whether the raw key names a device ``known`` does not know (a malformed key: False, the decoder refuses it)."""
    try:
        device = wire.device_from_key(prefix, key_expr, wire.Kind.RAW)
    except wire.WireError:
        return False
    return not known(device)
