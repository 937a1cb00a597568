"""Issue 32: the MAVLink edge grew 1-3 MB a flood round in ``magnet bench soak`` (79 -> 100 MB). pymavlink kept, per
system id, the last message of every type and instance (two copies per HIGHRES_IMU id: 65,280 (system id, id) pairs
possible), per (system, component) the last sequence number and every PARAM_VALUE by name, and every UDP address
that ever sent; the stream kept every system id it heard. Rounds of floods of new ids through the edge's own source
and status (a fake session): once their ids are forgotten, every per-sender structure is back to its size."""

from __future__ import annotations

import socket
import time
from typing import Any

from helpers import free_ports
from pymavlink.dialects.v20 import common as mav
from test_edge_device_limit import FakeSession

from magnet.autopilot import mavlink_stream
from services.edge.mavlink_source import MAX_UDP_CLIENTS, MavlinkSource
from services.edge.service import EdgeStatus
from services.edge.settings import EdgeSettings

SENDERS = MAX_UDP_CLIENTS + 8  # more addresses than a UDP server link keeps


def flood(round_no: int) -> list[bytes]:
    """HIGHRES_IMU from 60 system ids x 3 ids new to this round, each followed by a PARAM_VALUE of a made-up name."""
    out = []
    for sysid in range(2, 62):
        link = mav.MAVLink(None, srcSystem=sysid, srcComponent=1 + round_no)
        for imu_id in range(3 * round_no, 3 * round_no + 3):
            imu = mav.MAVLink_highres_imu_message(sysid, 0, 0, -9.8, 0, 0, 0, 0.2, 0.05, 0.4, 0, 0, 0, 20, 0, imu_id)
            param = link.param_value_encode(f"X{round_no}_{sysid}_{imu_id}".encode(), 1.0, 9, 100, 0)
            out += [imu.pack(link), param.pack(link)]
    return out


def send(
    source: MavlinkSource, port: int, datagrams: list[bytes], most_tokens: list[int], session: FakeSession
) -> None:
    """Each datagram from one of ``SENDERS`` sockets (new addresses each call), 60 at a time, each lot read by the
    source before the next (within the socket's buffer)."""
    sockets = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(SENDERS)]
    try:
        for start in range(0, len(datagrams), 60):
            expected = source.stream.counts["messages"] + len(datagrams[start : start + 60])
            for k, datagram in enumerate(datagrams[start : start + 60], start):
                sockets[k % SENDERS].sendto(datagram, ("127.0.0.1", port))
            deadline = time.monotonic() + 5
            while source.stream.counts["messages"] < expected and time.monotonic() < deadline:
                source.take(0, 0, lambda: False)
                most_tokens.append(len(session.tokens))
            assert source.stream.counts["messages"] == expected  # every datagram read
    finally:
        for sock in sockets:
            sock.close()


def sizes(source: MavlinkSource, status: EdgeStatus, session: FakeSession) -> dict[str, Any]:
    link = source.connection
    return {
        "link messages": sum(len(state.messages) for state in link.sysid_state.values()),
        "link systems": len(link.sysid_state),
        "link sequences": len(link.last_seq),
        "link params": sum(len(state.params) + 1 for state in link.param_state.values()),
        "link clients": len(link.clients),
        "stream vehicles": len(source.stream.vehicles),
        "stream devices": len(source.stream.pending),
        "source": (len(source.ids), len(source.healthy), len(source.logged)),
        "status": (len(status.ids), len(status.admitted), len(status.keys), len(status.tokens), len(session.tokens)),
    }


def test_rounds_of_id_floods_leave_the_link_the_stream_and_the_edge_as_they_were(monkeypatch: Any) -> None:
    monkeypatch.setattr(mavlink_stream, "FORGET_CHECK_NS", 50_000_000)  # the silent ids looked for every 50 ms, not 1 s
    [port] = free_ports(1)
    settings = EdgeSettings(mavlink=f"udpin:127.0.0.1:{port}", device="mavedge", forget_after_s=0.2)
    source = MavlinkSource(settings)
    status, session = EdgeStatus(settings, source), FakeSession()
    status.open(session)  # type: ignore[arg-type]
    source.attach(session, status)  # type: ignore[arg-type]
    after: list[dict[str, Any]] = []
    seen_devices: list[int] = []
    try:
        for round_no in range(2):
            tokens: list[int] = []
            send(source, port, flood(round_no), tokens, session)
            seen_devices.append(max(tokens))
            deadline = time.monotonic() + 5
            while (source.stream.pending or status.tokens) and time.monotonic() < deadline:
                source.take(0, 0, lambda: False)  # the flood's ids silent: forgotten
            after.append(sizes(source, status, session))
    finally:
        status.close()
        source.close()
    assert seen_devices == [64, 64]  # each flood filled the port's places (--max-port-devices)
    assert after[0] == after[1], after
    assert after[1] == {
        "link messages": 2,  # a fresh pymavlink state's MAV and HOME
        "link systems": 1,
        "link sequences": 0,
        "link params": 1,
        "link clients": MAX_UDP_CLIENTS,
        "stream vehicles": 0,
        "stream devices": 0,
        "source": (0, 0, 1),  # the one "device-limit" log line said once
        "status": (0, 0, 0, 0, 0),
    }
