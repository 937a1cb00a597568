"""The Foxglove WebSocket behind its front (issue 32: it accepted any Origin and asked for no token, so any web page
in the operator's browser could read the live fleet). A real foxglove-sdk server behind ``FoxgloveFront``, a client
speaking RFC 6455 and the Foxglove protocol (``tests/foxglove_ws_client.py``): a foreign Origin, a foreign Host, no
token or a wrong one are refused before the SDK's server sees a byte; the token in a header, as a subprotocol, or
the view token in the address get the Foxglove handshake and a message."""

from __future__ import annotations

import json
import socket
import threading

import foxglove
import pytest
from foxglove_ws_client import SUBPROTOCOLS, FoxgloveClient

from services.dashboard.foxglove_front import (
    FoxgloveFront,
    FrontCheck,
    Upgrade,
    private_loopback_host,
    view_token,
)
from services.dashboard.hosts import LOOPBACK_NAMES

TOKEN = "fox-s3cret"
BEARER = {"Authorization": f"Bearer {TOKEN}"}
TOPIC = "/magnet/front_test/heading"


@pytest.fixture
def front():
    private = private_loopback_host()
    server = foxglove.start_server(name="magnet-test", host=private, port=0)
    channel = foxglove.Channel(TOPIC, schema={"type": "object"})
    stop = threading.Event()

    def log_headings() -> None:
        while not stop.wait(0.05):
            channel.log({"heading_deg": 12.5})

    logger = threading.Thread(target=log_headings, daemon=True)
    logger.start()
    front = FoxgloveFront("127.0.0.1", 0, (private, server.port), FrontCheck(TOKEN, LOOPBACK_NAMES | {"robot.lan"}))
    yield front
    stop.set()
    logger.join(5)
    front.close()
    server.stop()


def refused(front, **kwargs) -> str:
    with pytest.raises(ConnectionError) as caught:
        FoxgloveClient("127.0.0.1", front.port, **kwargs).close()
    return str(caught.value)


def receives_a_heading(client: FoxgloveClient) -> bool:
    info, channels = client.wait_for_channel(TOPIC, 10)
    assert info["op"] == "serverInfo" and client.protocol in SUBPROTOCOLS
    client.send_json({"op": "subscribe", "subscriptions": [{"id": 3, "channelId": channels[TOPIC]["id"]}]})
    _, payload = client.message_data(3, 10)
    return json.loads(payload) == {"heading_deg": 12.5}


@pytest.mark.integration
def test_a_web_page_elsewhere_or_a_client_without_the_token_is_refused(front):
    assert "403" in refused(front, headers={**BEARER, "Origin": "https://evil.example"})
    assert "403" in refused(front, headers={"Origin": "null"})  # a sandboxed frame (or a desktop app) without it
    assert "403" in refused(front, headers={**BEARER, "Host": "rebound.evil.example:8765"})  # DNS rebinding
    assert "401" in refused(front)  # no token
    assert "401" in refused(front, headers={"Authorization": "Bearer wrong"})
    assert "401" in refused(front, path=f"/?token={TOKEN}")  # the control token never in an address
    assert "401" in refused(front, headers={"Origin": "http://localhost:8080"})  # a good Origin is not a token
    with socket.create_connection(("127.0.0.1", front.port), timeout=5) as plain:
        plain.sendall(b"GET /api/fleet HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert plain.recv(64).startswith(b"HTTP/1.1 400")
    assert front.refused == {403: 3, 401: 4, 400: 1} and front.clients == 0


@pytest.mark.integration
@pytest.mark.parametrize(
    "how",
    [
        {"headers": BEARER},
        {"headers": {"X-Magnet-Token": TOKEN, "Origin": "http://127.0.0.1:8080"}},
        {"protocols": (*SUBPROTOCOLS, f"magnet-token.{TOKEN}")},
        {"path": f"/?token={view_token(TOKEN)}", "headers": {"Origin": "https://robot.lan"}},  # the Foxglove app
        {"headers": {**BEARER, "Host": "robot.lan:8765"}},
        {"path": f"/?token={view_token(TOKEN)}", "headers": {"Origin": "null"}},  # a desktop app's file:// window
    ],
    ids=["bearer", "x-magnet-token", "subprotocol", "view-token-in-address", "allowed-host", "desktop-app"],
)
def test_the_token_gets_the_foxglove_handshake_and_a_message(front, how):
    client = FoxgloveClient("127.0.0.1", front.port, **how)
    try:
        assert receives_a_heading(client)
    finally:
        client.close()


def test_what_the_sdk_server_gets_carries_no_token():
    check = FrontCheck(TOKEN, LOOPBACK_NAMES)
    request = Upgrade(
        b"GET /ws?token=abc HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nAuthorization: Bearer x\r\n"
        b"X-Magnet-Token: y\r\nSec-WebSocket-Protocol: foxglove.sdk.v1, magnet-token.z\r\n\r\n"
    )
    forwarded = check.forwarded(request).decode()
    assert forwarded.startswith("GET /ws HTTP/1.1\r\n") and "sec-websocket-protocol: foxglove.sdk.v1\r\n" in forwarded
    assert all(word not in forwarded.lower() for word in ("token", "authorization", "magnet-token"))
    assert view_token(TOKEN) != TOKEN and len(view_token(TOKEN)) == 22
    with pytest.raises(ValueError, match="twice"):
        check.refusal(Upgrade(b"GET / HTTP/1.1\r\nHost: a\r\nHost: b\r\nUpgrade: websocket\r\n\r\n"))
