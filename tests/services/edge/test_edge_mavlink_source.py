"""The edge's MAVLink source in-process on a loopback UDP port: a pymavlink sender's messages become batches, garbage
is dropped and counted with one log line and nothing ends, and the options are checked."""

from __future__ import annotations

import logging
import os
import pty
import socket
import time

import pytest
from helpers import free_ports
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from services.edge.mavlink_source import MavlinkSource
from services.edge.settings import EdgeSettings
from services.edge.sources import make_source


def test_options_are_checked() -> None:
    for options, text in (
        ({"emulate": True}, "takes no --emulate"),
        ({"device_prefix": "a/b"}, "device"),
        ({"vehicle_timeout_s": 0.0}, "--vehicle-timeout"),
        ({"baud": 1}, "--baud"),
    ):
        with pytest.raises(ValueError, match=text):
            EdgeSettings(mavlink="udpin:127.0.0.1:14550", **options)
    with pytest.raises(ValueError, match="needs a URL"):
        EdgeSettings(mavlink="")


def test_messages_become_batches_and_garbage_is_counted_once_in_the_log(caplog: pytest.LogCaptureFixture) -> None:
    [port] = free_ports(1)
    source = make_source(EdgeSettings(mavlink=f"udpin:127.0.0.1:{port}", batch=5, device_prefix="uav"))
    assert isinstance(source, MavlinkSource)
    sender = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=42, source_component=1)
    junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    batches = []
    try:
        with caplog.at_level(logging.WARNING, logger="magnet.edge"):
            for k in range(20):
                junk.sendto(bytes((k * 91 + i * 7) % 256 for i in range(80)), ("127.0.0.1", port))
                sender.mav.scaled_imu3_send(10 * k, 0, 0, -1000, 0, 0, 0, 190, -30, 420)
                time.sleep(0.002)
            deadline = time.monotonic() + 5
            while source.stream.counts["samples"] < 20 and time.monotonic() < deadline:
                batches += source.take(0, 0, lambda: False)
                if batches and source.stream.counts["messages"] >= 20 and not source.take(0, 0, lambda: False):
                    break
            batches += source.take(0, 0, lambda: True)  # stopping: what waits goes out
    finally:
        junk.close()
        sender.close()
        source.close()
    # a garbage datagram may end in what looks like the start of a frame and swallow the next real message with it
    got = sum(len(b) for b in batches)
    assert 15 <= got <= 20 and {b.device for b in batches} == {"uav42-mag2"}
    assert [b.seq for b in batches] == list(range(len(batches)))
    reads = source.status()
    assert reads["dropped"]["bad-data"] > 0 and reads["samples"] == got and reads["vehicles"] == [42]
    assert source.ids == ["uav42-mag2"]
    garbage_lines = [r for r in caplog.records if "bad-data" in r.getMessage()]
    assert len(garbage_lines) == 1


def test_a_serial_device_is_read_at_its_baud_rate() -> None:
    """A pseudo-terminal stands in for a flight controller on USB: pymavlink opens it through pyserial."""
    master, slave = pty.openpty()
    try:
        source = make_source(EdgeSettings(mavlink=os.ttyname(slave), baud=115200, batch=2))
        sender = mav.MAVLink(None, srcSystem=3, srcComponent=1)
        for k in range(2):
            os.write(master, sender.scaled_imu_encode(20 * k, 0, 0, -1000, 0, 0, 0, 200, 0, 400).pack(sender))
        batches: list = []
        deadline = time.monotonic() + 5
        while not batches and time.monotonic() < deadline:
            batches += source.take(0, 0, lambda: False)
        source.close()
    finally:
        os.close(master)
        os.close(slave)
    assert [(b.device, len(b)) for b in batches] == [("mav3-mag0", 2)]


def test_a_link_that_cannot_be_opened_is_one_clear_error() -> None:
    with pytest.raises(ValueError, match="cannot open it"):
        make_source(EdgeSettings(mavlink="/dev/no-such-flight-controller"))
    for url in ("udpin:127.0.0.1:99999", "tcp:127.0.0.1", "udpout::14550"):
        with pytest.raises(ValueError, match="HOST:PORT"):
            EdgeSettings(mavlink=url)
