"""The twin's cuttable link (twin/relay.py) over real UNIX sockets: forwards, swallows while cut
(nothing closed, like a pulled cable), drops the connections that lived through a cut on restore."""

import os
import socket
import threading

import pytest

from twin.relay import RelayHub


@pytest.fixture
def echo_server(tmp_path):
    """A UNIX stream server that echoes every byte (stands in for the router)."""
    path = str(tmp_path / "router.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen()
    stop = threading.Event()

    def serve(conn: socket.socket) -> None:
        with conn:
            while data := conn.recv(4096):
                conn.sendall(data)

    def accept() -> None:
        while not stop.is_set():
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    yield path
    stop.set()
    srv.close()


def _connect(path: str) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(5.0)
    s.connect(path)
    return s


def test_forward_cut_restore(tmp_path, echo_server):
    hub = RelayHub()
    try:
        relay = hub.add("h1", str(tmp_path / "h1.link"), echo_server)
        assert relay.endpoint == f"unixsock-stream/{tmp_path / 'h1.link'}"
        a = _connect(relay.listen)
        a.sendall(b"ping")
        assert a.recv(16) == b"ping"

        hub.set_cut("h1", True)
        a.sendall(b"lost")
        a.settimeout(0.5)
        with pytest.raises(socket.timeout):  # swallowed, and the socket stays open
            a.recv(16)
        b = _connect(relay.listen)           # a new connection over a cut link: accepted, silent
        b.settimeout(0.5)
        b.sendall(b"hello?")
        with pytest.raises(socket.timeout):
            b.recv(16)

        hub.set_cut("h1", False)
        a.settimeout(5.0)
        b.settimeout(5.0)
        assert a.recv(16) == b"" and b.recv(16) == b""  # streams that lost bytes are closed
        c = _connect(relay.listen)
        c.sendall(b"again")
        assert c.recv(16) == b"again"
        assert relay.connections == 3
        for s in (a, b, c):
            s.close()
    finally:
        hub.close()
    assert not os.path.exists(tmp_path / "h1.link")


def test_router_down_closes_the_agent_side_so_it_retries(tmp_path):
    hub = RelayHub()
    try:
        relay = hub.add("h1", str(tmp_path / "h1.link"), str(tmp_path / "absent.sock"))
        a = _connect(relay.listen)
        assert a.recv(16) == b""
        a.close()
    finally:
        hub.close()


def test_tcp_link_for_tls_forwards_and_cuts():
    """A secure twin's link: loopback TCP both ways (TLS runs over TCP only), the port picked by the OS."""
    srv = socket.create_server(("127.0.0.1", 0))
    port = srv.getsockname()[1]

    def echo() -> None:
        conn, _ = srv.accept()
        with conn:
            while data := conn.recv(4096):
                conn.sendall(data)

    threading.Thread(target=echo, daemon=True).start()
    hub = RelayHub()
    try:
        relay = hub.add("h1", ("127.0.0.1", 0), ("127.0.0.1", port))
        assert isinstance(relay.listen, tuple) and relay.listen[1] > 0
        assert relay.endpoint == f"tcp/127.0.0.1:{relay.listen[1]}"
        a = socket.create_connection(relay.listen, timeout=5.0)
        a.sendall(b"hello")
        assert a.recv(16) == b"hello"
        hub.set_cut("h1", True)
        a.sendall(b"lost")
        a.settimeout(0.5)
        with pytest.raises(socket.timeout):
            a.recv(16)
        hub.set_cut("h1", False)
        a.settimeout(5.0)
        assert a.recv(16) == b""  # the stream that lost bytes is closed
        a.close()
    finally:
        hub.close()
        srv.close()
