"""A minimal Foxglove WebSocket protocol client, written for the tests from the published specifications: RFC 6455
(the WebSocket handshake and framing) and foxglove/ws-protocol ``docs/spec.md`` (subprotocol ``foxglove.sdk.v1``,
formerly ``foxglove.websocket.v1``; JSON text messages with an ``op``: ``serverInfo``, ``advertise``, ``subscribe``;
binary Message Data: opcode 0x01, uint32 subscription id, uint64 receive time in ns, then the payload,
little-endian)."""

from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import struct
import time
from typing import Any

#: the spec's subprotocol: named foxglove.websocket.v1 first, foxglove.sdk.v1 in its current text (the same messages);
#: offered both, the server picks one (foxglove-sdk 0.30 accepts only the current name)
SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
_GUID = "258EAFA5-E914-47DA-95CA-C5AB0DC85B11"  # RFC 6455, section 1.3


class FoxgloveClient:
    def __init__(
        self,
        host: str,
        port: int,
        timeout_s: float = 10.0,
        path: str = "/",
        headers: dict[str, str] | None = None,
        protocols: tuple[str, ...] = SUBPROTOCOLS,
    ) -> None:
        """Connect and upgrade (``headers`` added to the request, ``Host`` replaced when it names one);
        ConnectionError naming the status line when the server refuses."""
        self.sock = socket.create_connection((host, port), timeout=timeout_s)
        key = base64.b64encode(os.urandom(16)).decode()
        fields = {"Host": f"{host}:{port}", "Upgrade": "websocket", "Connection": "Upgrade"}
        fields |= {
            "Sec-WebSocket-Key": key,
            "Sec-WebSocket-Version": "13",
            "Sec-WebSocket-Protocol": ", ".join(protocols),
        }
        fields |= headers or {}
        request = f"GET {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in fields.items()) + "\r\n"
        try:
            self._handshake(request, key)
        except BaseException:
            self.sock.close()
            raise

    def _handshake(self, request: str, key: str) -> None:
        self.sock.sendall(request.encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(1)
            if not chunk:
                raise ConnectionError("closed during the handshake")
            head += chunk
        lines = head.decode().split("\r\n")
        headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
        if " 101 " not in lines[0] + " ":
            raise ConnectionError(f"no upgrade: {lines[0]}")
        accept = base64.b64encode(hashlib.sha1((key + _GUID).encode()).digest()).decode()
        self.protocol = headers.get("sec-websocket-protocol")
        if headers.get("sec-websocket-accept") != accept:
            raise ConnectionError("wrong Sec-WebSocket-Accept")

    def _exact(self, n: int) -> bytes:
        data = b""
        while len(data) < n:
            chunk = self.sock.recv(n - len(data))
            if not chunk:
                raise ConnectionError("closed")
            data += chunk
        return data

    def receive(self) -> tuple[int, bytes]:
        """The next whole message: (opcode 1 text or 2 binary, payload); control frames are skipped."""
        parts, first_opcode = [], None
        while True:
            b0, b1 = self._exact(2)
            fin, opcode, size = b0 & 0x80, b0 & 0x0F, b1 & 0x7F
            if size == 126:
                size = struct.unpack(">H", self._exact(2))[0]
            elif size == 127:
                size = struct.unpack(">Q", self._exact(8))[0]
            mask = self._exact(4) if b1 & 0x80 else None
            payload = self._exact(size)
            if mask:
                payload = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
            if opcode >= 8:  # close, ping, pong
                if opcode == 8:
                    raise ConnectionError("closed by the server")
                continue
            first_opcode = first_opcode or opcode
            parts.append(payload)
            if fin:
                return first_opcode, b"".join(parts)

    def send_json(self, message: dict[str, Any]) -> None:
        data, mask = json.dumps(message).encode(), os.urandom(4)
        size = len(data)
        header = bytes([0x81]) + (bytes([0x80 | size]) if size < 126 else bytes([0x80 | 126]) + struct.pack(">H", size))
        self.sock.sendall(header + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(data)))

    def wait_for_channel(self, topic: str, timeout_s: float) -> tuple[dict[str, Any], dict[str, Any]]:
        """(the serverInfo, the advertised channel of ``topic``) as they arrive."""
        deadline, info, channels = time.monotonic() + timeout_s, {}, {}
        while time.monotonic() < deadline:
            opcode, payload = self.receive()
            if opcode != 1:
                continue
            message = json.loads(payload)
            if message["op"] == "serverInfo":
                info = message
            elif message["op"] == "advertise":
                channels.update({c["topic"]: c for c in message["channels"]})
                if topic in channels:
                    return info, channels
        raise TimeoutError(f"{topic} was not advertised")

    def message_data(self, subscription: int, timeout_s: float) -> tuple[int, bytes]:
        """(receive time ns, payload) of the next Message Data of ``subscription``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            opcode, payload = self.receive()
            if opcode == 2 and payload[0] == 0x01:
                sub_id, t_ns = struct.unpack_from("<IQ", payload, 1)
                if sub_id == subscription:
                    return t_ns, payload[13:]
        raise TimeoutError("no message data")

    def close(self) -> None:
        self.sock.close()
