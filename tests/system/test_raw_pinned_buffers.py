"""Issue 32's soak: a fresh calibrator peaked 81-97 MB after its first flood and the compass 84-109 MB, wider than
the soak's rule. A Zenoh sample keeps the whole receive batch it arrived in alive (64 kB by default, however small the
message), and the raw channel of 256 (``CHANNEL_CAPACITY``) fills with such samples whenever the intake's pump is
starved of CPU. Behind a router the calibrator and the compass declare their raw subscriber on a session of their own
whose link carries batches of 8 kB (``zenoh_session.raw_session``), so a full channel holds about 2 MB, not 16.

In this process: a router, the service's session and its raw session (its own defaults) as clients, and a publisher
sending one message a batch (express) until the raw channel is full; what the waiting samples hold is the RSS given
back when they are taken and let go. With the service's main session (64 kB batches) the same held 12 MB."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Mapping

import pytest
import zenoh
from helpers import free_ports, held_by_waiting_samples

from services.calibrator import service as calibrator_service
from services.common.allocator import give_back_freed_memory
from services.common.zenoh_session import ZenohSettings, open_session, raw_session
from services.compass import service as compass_service

pytestmark = pytest.mark.integration

#: each service: its session's defaults (the raw session's start from them) and its raw channel's capacity
SERVICES: dict[str, tuple[Mapping[str, str] | None, int]] = {
    "calibrator": (None, calibrator_service.CHANNEL_CAPACITY),
    "compass": (compass_service.ZENOH_DEFAULTS, compass_service.CHANNEL_CAPACITY),
}


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_raw_samples_waiting_in_the_channel_hold_little_more_than_their_bytes(name: str) -> None:
    defaults, capacity = SERVICES[name]
    give_back_freed_memory()  # as the service's main does (a process's allocator settings; harmless in a test run)
    (port,) = free_ports(1)
    router = ZenohSettings(mode="router", listen=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    client = ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    payload = bytes(300)  # about a raw batch of a few samples
    with contextlib.ExitStack() as stack:
        stack.enter_context(open_session(router))
        sender = stack.enter_context(open_session(client))
        session = stack.enter_context(open_session(client, defaults))
        raw = raw_session(stack, session, client, defaults)
        assert raw is not session, "behind a router the raw subscriber has a session of its own"
        subscriber = stack.enter_context(raw.declare_subscriber("magnet/*/raw", zenoh.handlers.FifoChannel(capacity)))
        publisher = stack.enter_context(  # one message a batch, none dropped on the way (the router waits for room)
            sender.declare_publisher("magnet/d/raw", express=True, congestion_control=zenoh.CongestionControl.BLOCK)
        )
        deadline = time.monotonic() + 10
        while not publisher.matching_status.matching and time.monotonic() < deadline:  # type: ignore[attr-defined]
            time.sleep(0.02)
        # the pump held: the channel fills, then drains
        taken, held_mb = held_by_waiting_samples(publisher, subscriber.handler, capacity, payload, 0.0003)
    assert taken >= capacity * 0.9, taken
    # 256 samples of 300 bytes: 12 MB held in 64 kB batches (measured), about 2 MB in 8 kB ones
    assert held_mb < 5.0, f"{taken} waiting samples held {held_mb:.1f} MB"
