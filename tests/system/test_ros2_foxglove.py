"""``magnet dashboard --foxglove``: a client speaking the Foxglove WebSocket protocol (written from its published
spec, ``tests/foxglove_ws_client.py``) sees the fleet's channels advertised with their schemas, subscribes to a
device's heading and decodes it; the attitude goes out as ``foxglove.FrameTransform``."""

from __future__ import annotations

import json
import threading

import pytest
from foxglove_ws_client import SUBPROTOCOLS, FoxgloveClient
from helpers import connect_args, free_ports, listen_args, wait_for
from test_ros2_compass import collect_headings

from services.dashboard.foxglove_front import view_token

pytestmark = pytest.mark.integration
TOKEN = "fox-token-1"


def wait_until(seconds: float):
    """Yield every 0.05 s until ``seconds`` have passed (a caller stops early with ``any``/``break``)."""
    import time

    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        yield
        time.sleep(0.05)


def test_a_foxglove_client_subscribes_to_a_devices_heading_and_decodes_it(procs):
    comp_port, edge_port, dash_port, http_port, fox_port = free_ports(5)
    procs.start("compass", "compass", *listen_args(comp_port))
    procs.start(
        "edge", "edge", "--emulate", "--devices", "1", "--device", "fox", "--gyro", "--rate", "50", "--batch", "5",
        *listen_args(edge_port), *connect_args(comp_port),
    )  # fmt: skip
    procs.start(
        "dashboard", "dashboard", "--http", f"127.0.0.1:{http_port}", "--foxglove", f"127.0.0.1:{fox_port}",
        "--token", TOKEN, *listen_args(dash_port), *connect_args(comp_port),
    )  # fmt: skip
    wait_for(lambda: "Foxglove WebSocket" in procs.log("dashboard"), 20, "the Foxglove server")
    # issue 32: any web page in the operator's browser could read the fleet; now the token and a known Origin
    for headers in ({}, {"Authorization": f"Bearer {TOKEN}", "Origin": "https://evil.example"}):
        with pytest.raises(ConnectionError, match=r"40[13]"):
            FoxgloveClient("127.0.0.1", fox_port, headers=headers)
    assert f"ws://127.0.0.1:{fox_port}/?token={view_token(TOKEN)}" in procs.log("dashboard")
    ours: dict[int, tuple] = {}
    stop = threading.Event()
    watcher = threading.Thread(target=collect_headings, args=(comp_port, stop, ours, "fox-000"), daemon=True)
    watcher.start()
    client = FoxgloveClient("127.0.0.1", fox_port, path=f"/?token={view_token(TOKEN)}")  # as the Foxglove app does
    try:
        assert client.protocol in SUBPROTOCOLS
        info, channels = client.wait_for_channel("/magnet/xfox_2d000/heading", 30)
        heading_channel = channels["/magnet/xfox_2d000/heading"]
        assert (
            heading_channel["encoding"] == "json" and json.loads(heading_channel["schema"])["title"] == "magnet.Heading"
        )
        if "/tf" not in channels:
            channels.update(client.wait_for_channel("/tf", 10)[1])
        assert channels["/tf"]["schemaName"] == "foxglove.FrameTransform"
        wait_for(lambda: ours, 30, "magnet's own headings")  # the watcher is live before the client subscribes
        client.send_json({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": heading_channel["id"]}]})
        for _ in range(50):  # the first may be one the watcher missed (before it was live, or dropped on a busy host)
            received_ns, payload = client.message_data(7, 20)
            heading = json.loads(payload)
            if any(heading["t_ns"] in ours for _ in wait_until(2.0)):
                break
        wait_for(lambda: heading["t_ns"] in ours, 10, "magnet's own heading of that sample")
    finally:
        client.close()
        stop.set()
        watcher.join(timeout=10)
    assert info["op"] == "serverInfo" and received_ns > 0
    _, true_heading, pitch, roll, _ = ours[heading["t_ns"]]  # the same values as magnet's own heading message
    assert heading["true_heading_deg"] == pytest.approx(true_heading, abs=1e-3)
    assert heading["pitch_deg"] == pytest.approx(pitch, abs=1e-3)
    assert heading["roll_deg"] == pytest.approx(roll, abs=1e-3)
    assert 0 <= heading["true_heading_deg"] < 360 and -90 <= heading["pitch_deg"] <= 90
    assert (heading["ros_yaw_deg"] - (90 - heading["true_heading_deg"]) + 180) % 360 == pytest.approx(180, abs=1e-6)
    assert procs.alive("dashboard")
