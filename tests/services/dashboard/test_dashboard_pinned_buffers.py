"""Issue 32's soak: the dashboard's memory rose 20-40 MB within each flood's burst (native, not Python objects). A
Zenoh sample keeps the receive buffer it arrived in alive, and that buffer is a whole batch (the link's batch size,
64 kB by default) however small the message: the rings of 1,024 headings and 1,024 progress messages that wait
between two ticks held up to 64 MB each when a burst arrived one message a batch. The dashboard's session asks for
smaller batches (``service.ZENOH_DEFAULTS``), which its link negotiates down for both directions.

Two sessions on loopback in this process: the dashboard's session (its defaults) with a ring of the ingest's
capacity, and a publisher sending one message a batch (express). What the waiting samples hold is the RSS given back
when they are taken and let go."""

from __future__ import annotations

import time

import pytest
import zenoh
from helpers import free_ports, held_by_waiting_samples

from services.common.allocator import give_back_freed_memory
from services.common.zenoh_session import ZenohSettings, open_session
from services.dashboard import ingest, service

pytestmark = pytest.mark.integration


def test_samples_waiting_in_a_ring_hold_little_more_than_their_bytes() -> None:
    give_back_freed_memory()  # as the service's main does (a process's allocator settings; harmless in a test run)
    (port,) = free_ports(1)
    listen = ZenohSettings(listen=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    connect = ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",), no_multicast_scouting=True)
    capacity = ingest.RING_CAPACITY
    payload = bytes(300)  # about a heading message of one device
    with open_session(listen, service.ZENOH_DEFAULTS) as dashboard, open_session(connect) as sender:
        ring = zenoh.handlers.RingChannel(capacity)
        with dashboard.declare_subscriber("magnet/*/heading", ring) as subscriber:
            publisher = sender.declare_publisher("magnet/d/heading", express=True)  # one message, one batch
            deadline = time.monotonic() + 10
            while not publisher.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.02)
            # the ring fills, then drains
            taken, held_mb = held_by_waiting_samples(publisher, subscriber.handler, capacity, payload, 0.0002)
            publisher.undeclare()
    assert taken >= capacity * 0.9, taken
    # 1,024 samples of 300 bytes: 64 MB held in 64 kB batches, at most 8 MB in the dashboard's 8 kB ones
    assert held_mb < 16.0, f"{taken} waiting samples held {held_mb:.1f} MB"
