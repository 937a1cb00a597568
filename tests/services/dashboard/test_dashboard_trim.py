"""Issue 32's soak: after each flood of ids the dashboard kept 17-30 MB of freed heap (Zenoh's receive buffers, the
burst's decoded batches) until its next trim, up to ``TRIM_S`` (10 s) later, and the soak saw those plateaus as the
round's highest RSS. A step that took a burst now gives the heap back within ``TRIM_BUSY_S``, during the burst and
once after it; quiet steps keep the period. No network: a stand-in session holds the samples."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from magnet import wire
from services.dashboard import ingest
from services.dashboard.state import FleetState


class Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


class Sample:
    def __init__(self, key: str, data: bytes) -> None:
        self.key_expr, self.payload = key, Payload(data)


class Channel:
    def __init__(self) -> None:
        self.samples: list[Sample] = []

    def try_recv(self) -> Sample | None:
        return self.samples.pop(0) if self.samples else None

    def __enter__(self) -> Channel:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


class Session:
    def __init__(self) -> None:
        self.channels: dict[str, Channel] = {}

    def liveliness(self) -> Session:
        return self

    def declare_subscriber(self, key: str, handler: Any, **kwargs: Any) -> Channel:
        return self.channels.setdefault(key, Channel())

    def get(self, *args: Any, **kwargs: Any) -> Channel:
        return Channel()


def headings(count: int) -> list[Sample]:
    n = 2
    out = []
    for i in range(count):
        batch = wire.HeadingBatch(
            f"flood-{i}", 0, np.arange(n, dtype=np.int64), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n),
            np.ones((n, 3)) * 30.0, 0.0, "", np.zeros(n, dtype=np.int64),
        )  # fmt: skip
        out.append(Sample(f"magnet/flood-{i}/heading", wire.encode_heading(batch)))
    return out


BURST, WITHIN_S = 500, 1.0  # a step of this many messages is a burst; its heap given back within this long


def test_a_burst_gives_the_freed_heap_back_within_a_second_not_the_period(monkeypatch: pytest.MonkeyPatch) -> None:
    trims: list[float] = []

    def give_back_now() -> bool:
        trims.append(time.monotonic())
        return True

    monkeypatch.setattr(ingest, "give_back_now", give_back_now)
    session = Session()
    state = FleetState()
    with ingest.Ingest(session, "magnet", state) as feed:  # type: ignore[arg-type]
        heading_channel = session.channels["magnet/*/heading"]
        feed.trim.trimmed_s = time.monotonic() - WITHIN_S  # the last trim a second ago: not due by the period
        heading_channel.samples = headings(BURST)
        feed.step()
        assert len(state.rows) == BURST
        assert len(trims) == 1  # the burst's heap given back at once (before: only TRIM_S after the last trim)
        heading_channel.samples = headings(BURST)
        feed.step()
        assert len(trims) == 1  # not more than once every TRIM_BUSY_S
        feed.trim.trimmed_s -= WITHIN_S
        feed.step()  # quiet now: once more after the burst
        assert len(trims) == 2
        feed.trim.trimmed_s -= WITHIN_S
        feed.step()
        assert len(trims) == 2  # quiet steps keep the period
        feed.trim.trimmed_s -= ingest.TRIM_S
        feed.step()
        assert len(trims) == 3
    assert (ingest.TRIM_BUSY_MESSAGES, ingest.TRIM_BUSY_S) == (BURST, WITHIN_S)


def test_a_bomb_refused_by_its_size_gives_the_heap_back_within_a_second(monkeypatch: pytest.MonkeyPatch) -> None:
    """A raw payload over a raw message's size is refused uncopied, but Zenoh reassembled its MBs in the heap: the
    soak's 20 bombs of 4 MB left it freed and kept until the periodic trim, like a flood's burst."""
    trims: list[float] = []
    monkeypatch.setattr(ingest, "give_back_now", lambda: trims.append(time.monotonic()) or True)
    session = Session()
    state = FleetState()
    with ingest.Ingest(session, "magnet", state) as feed:  # type: ignore[arg-type]
        raw_channel = session.channels["magnet/*/raw"]
        feed.trim.trimmed_s = time.monotonic() - WITHIN_S
        raw_channel.samples = [Sample("magnet/s0-000/raw", b"\x90" * (wire.RAW_LIMITS.payload_bytes + 1))]
        feed.step()
        assert state.dropped.counts.get("raw:oversized") == 1
        assert len(trims) == 1  # at once (before: only TRIM_S after the last trim)
        feed.trim.trimmed_s -= WITHIN_S
        feed.step()
        assert len(trims) == 1  # no burst since: the period again
