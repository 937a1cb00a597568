"""Where the dashboard is served when no --http is given: 8080 while it is free, including just after a server on it
stopped (TIME_WAIT, as when ``magnet up`` is restarted within a minute), else a free loopback port rather than a
failure after the address was printed (``magnet up`` holds 8080)."""

import socket

from services.dashboard.settings import bindable, default_http


def _listening() -> socket.socket:
    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen()
    return server


def test_a_taken_port_gives_another_free_one():
    with _listening() as server:
        taken = f"127.0.0.1:{server.getsockname()[1]}"
        assert not bindable(taken)
        other = default_http(taken)
        assert other != taken and bindable(other)


def test_a_port_just_released_by_a_server_counts_as_free():
    server = _listening()
    address = f"127.0.0.1:{server.getsockname()[1]}"
    with socket.create_connection(server.getsockname()) as client:
        accepted, _ = server.accept()
        accepted.close()  # the server closes first: its side of the connection waits in TIME_WAIT
        server.close()
        client.recv(1)
    assert bindable(address) and default_http(address) == address
