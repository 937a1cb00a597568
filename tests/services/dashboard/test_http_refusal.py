"""Issue 32's soak: under a burst of 2,000 event streams on a busy machine, connections closed to admit newer ones
(``http_limits.MAX_WAITING``) were dropped without an answer although their request had arrived (19 of 8,000 in a
4-minute soak): a lost request. Such a connection is now answered 503 first; one that sent nothing is closed as
before (nothing to answer)."""

from __future__ import annotations

import socket
from typing import Any

from services.dashboard.http_limits import REFUSAL, BoundedH11


class Transport:
    def __init__(self, sock: socket.socket) -> None:
        self.sock, self.written, self.closed = sock, b"", False

    def get_extra_info(self, name: str) -> Any:
        return self.sock if name == "socket" else None

    def is_closing(self) -> bool:
        return self.closed

    def write(self, data: bytes) -> None:
        self.written += data

    def close(self) -> None:
        self.closed = True


def waiting_connection(sock: socket.socket) -> tuple[BoundedH11, Transport]:
    protocol = BoundedH11.__new__(BoundedH11)  # only what closing an idle connection touches
    transport = Transport(sock)
    protocol.transport, protocol.cycle, protocol._head_timer = transport, None, None  # type: ignore[assignment]
    return protocol, transport


def test_a_connection_closed_for_a_newer_one_with_its_request_unread_is_answered_503() -> None:
    server, client = socket.socketpair()
    quiet_server, quiet_client = socket.socketpair()
    late_server, late_client = socket.socketpair()
    try:
        client.sendall(b"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        protocol, transport = waiting_connection(server)
        protocol._close_idle(refuse=True)
        assert transport.closed and transport.written == REFUSAL
        head, body = REFUSAL.split(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503 ") and f"content-length: {len(body)}".encode() in head
        assert server.recv(100).startswith(b"GET /api/stream")  # peeked, not taken
        idle, idle_transport = waiting_connection(quiet_server)  # sent nothing: closed without a word
        idle._close_idle(refuse=True)
        assert idle_transport.closed and idle_transport.written == b""
        late, late_transport = waiting_connection(late_server)  # its head's deadline: closed as before
        late._close_idle()
        assert late_transport.closed and late_transport.written == b""
    finally:
        for sock in (server, client, quiet_server, quiet_client, late_server, late_client):
            sock.close()
