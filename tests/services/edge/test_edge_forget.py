"""Issue 32: a MAVLink flood of ids fills an edge's places (``--max-port-devices``, ``--max-devices``); once those
ids fall silent for ``--forget-after`` they are forgotten (tokens withdrawn, places free) and a real vehicle that
comes later gets in. A real ``magnet edge --mavlink`` on loopback, the flood and the vehicle from
``services.bench.front_loads``."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import Processes, _loopback_client_config, free_ports, listen_args, liveliness_keys, wait_for

from magnet import wire
from services.bench.front_loads import mavlink_flood, vehicle

pytestmark = pytest.mark.integration


def edge_status(port: int) -> dict[str, Any]:
    with zenoh.open(_loopback_client_config(port)) as session:
        for reply in session.get(wire.status_key("magnet", "edge-dev"), timeout=2.0):
            if reply.ok is not None:
                answer = wire.unpack(reply.ok.payload.to_bytes())
                assert isinstance(answer, dict)
                return answer
    return {}


def test_a_flood_that_falls_silent_frees_its_places_for_a_real_vehicle(procs: Processes, tmp_path: Path) -> None:
    udp, edge_port = free_ports(2)
    limits = ["--max-port-devices", "4", "--max-devices", "4", "--forget-after", "2", "--batch", "5"]
    procs.start(
        "edge", "edge", "--mavlink", f"udpin:127.0.0.1:{udp}", "--device", "dev", *limits, *listen_args(edge_port)
    )
    wait_for(lambda: edge_status(edge_port), 20, "the edge's status")
    mavlink_flood(udp, 200, 2_000.0)  # 200 ids: 4 take the places, the rest are dropped
    flooded = wait_for(lambda: (s := edge_status(edge_port)) and s["devices"] == 4 and s, 10, "4 flood devices")
    assert flooded["reads"]["dropped"]["device-limit"] >= 150
    gone = wait_for(lambda: (s := edge_status(edge_port)) and s["devices"] == 0 and s, 10, "the silent ids forgotten")
    assert gone["reads"]["forgotten"] == 4 and gone["forgotten"] == 4
    assert not {k for k in liveliness_keys(edge_port) if "/device/mav" in k}  # their tokens withdrawn
    sender = threading.Thread(target=vehicle, args=(udp, 1, 3.0))
    sender.start()
    try:
        real = wait_for(lambda: (s := edge_status(edge_port)) and s["devices"] == 1 and s, 10, "the real vehicle")
        assert real["reads"]["vehicles"][0] == 1 and "mav1-mag1" in real["reads"]["hardware_ids"]
        assert "magnet/@alive/device/mav1-mag1" in liveliness_keys(edge_port)
    finally:
        sender.join()
