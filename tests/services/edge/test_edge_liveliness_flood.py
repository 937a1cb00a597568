"""Issue 32: one MAVLink port made 15,879 devices in 2 minutes, and their 32,000 liveliness tokens made wildcard
liveliness queries return nothing. A real ``magnet edge --mavlink`` with its default bounds, a real vehicle sending,
then the soak's flood of 20,000 (system id, id) pairs: a wildcard liveliness query still answers with the edge's
tokens, the real vehicle's among them, and at most a token and an unhealthy token per place
(``--max-port-devices``, 64 by default)."""

from __future__ import annotations

import threading

import pytest
from helpers import Processes, free_ports, listen_args, liveliness_keys, wait_for
from test_edge_forget import edge_status

from services.bench.front_loads import mavlink_flood, vehicle
from services.edge.settings import EdgeSettings

pytestmark = pytest.mark.integration


def test_a_flood_of_ids_leaves_wildcard_liveliness_queries_answered_and_tokens_bounded(procs: Processes) -> None:
    udp, edge_port = free_ports(2)
    places = EdgeSettings(mavlink=f"udpin:127.0.0.1:{udp}").max_port_devices
    procs.start("edge", "edge", "--mavlink", f"udpin:127.0.0.1:{udp}", "--device", "dev", *listen_args(edge_port))
    wait_for(lambda: edge_status(edge_port), 20, "the edge's status")
    sender = threading.Thread(target=vehicle, args=(udp, 1, 20.0))
    sender.start()
    try:
        wait_for(lambda: "magnet/@alive/device/mav1-mag1" in liveliness_keys(edge_port), 10, "the real vehicle")
        mavlink_flood(udp, 20_000, 5_000.0)
        full = wait_for(lambda: (s := edge_status(edge_port)) and s["devices"] == places and s, 10, "places full")
        keys = liveliness_keys(edge_port, "magnet/@alive/**", timeout_s=5.0)
    finally:
        sender.join()
    assert full["reads"]["dropped"]["device-limit"] > 10_000  # the rest of the flood: counted, no token
    assert {"magnet/@alive/edge/dev", "magnet/@alive/device/mav1-mag1"} <= keys
    device_tokens = [k for k in keys if k.startswith("magnet/@alive/device/")]
    assert places <= len(device_tokens) <= 2 * places + 1  # each place's token (and unhealthy one), the edge's own
