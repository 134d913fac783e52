"""Transports over a real pty (pyserial) and a real loopback socket."""

from __future__ import annotations

import logging
import socket
import threading

import pytest
from cgamap.drivers.sim.pty_device import PtyDevice
from cgamap.drivers.transport import (
    SerialTransport,
    SpyTransport,
    TcpTransport,
    TransportError,
    open_transport,
)


@pytest.fixture
def pty(tmp_path):
    dev = PtyDevice(str(tmp_path / "ttySIM"))
    yield dev
    dev.close()


def test_serial_roundtrip_all_bytes(pty):
    with open_transport(f"serial://{pty.path}?baud=38400", 0.5) as t:
        assert isinstance(t, SerialTransport)
        assert pty.host_baud() == 38400
        t.write(bytes(range(256)))
        got = b""
        while len(got) < 256:
            chunk = pty.read(4096, 1.0)
            assert chunk
            got += chunk
        assert got == bytes(range(256))
        pty.write(bytes(range(255, -1, -1)))
        assert t.read_exactly(256, 1.0) == bytes(range(255, -1, -1))
        t.set_baud(500000)
        assert pty.host_baud() == 500000


def test_plain_path_default_baud_and_read_until(pty):
    with open_transport(pty.path, 0.3) as t:
        assert pty.host_baud() == 9600
        pty.write(b"abc\n\ndef")
        assert t.read_until(b"\n\n") == b"abc\n\n"
        assert t.read(10) == b"def"
        assert t.read(10, 0.05) == b""           # timeout, no data
        pty.write(b"12345")
        assert t.read_until(b"\n", max_bytes=3) == b"123"
        assert t.read_until(b"\n", timeout=0.05) == b"45"


def test_unplug_raises_transport_error_and_replug(pty):
    t = open_transport(pty.path, 0.2)
    pty.disconnect()
    with pytest.raises(TransportError):
        for _ in range(5):
            t.read(1)
    t.close()
    with pytest.raises(TransportError, match="cannot open"):
        open_transport(pty.path)
    pty.reconnect()
    with open_transport(pty.path, 0.5) as t2:
        pty.write(b"back")
        assert t2.read_exactly(4) == b"back"


def test_open_errors_are_transport_errors():
    for url in ("", "gopher://x", "tcp://127.0.0.1", "/dev/does-not-exist-cgamap",
                "serial:///dev/null-x?baud=fast"):
        with pytest.raises(TransportError):
            open_transport(url)
    assert issubclass(TransportError, OSError)
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(TransportError, match="cannot connect"):
        open_transport(f"tcp://127.0.0.1:{port}")


def test_tcp_roundtrip_and_peer_close():
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]
    got: list[bytes] = []

    def serve():
        conn, _ = srv.accept()
        conn.settimeout(2.0)
        got.append(conn.recv(100))
        conn.sendall(b"pong\x03tail")
        conn.close()

    th = threading.Thread(target=serve, daemon=True)
    th.start()
    with open_transport(f"tcp://127.0.0.1:{port}", 1.0) as t:
        assert isinstance(t, TcpTransport)
        t.write(b"ping")
        assert t.read_until(b"\x03") == b"pong\x03"
        assert t.read_exactly(4) == b"tail"
        with pytest.raises(TransportError, match="closed"):
            t.read(10, 1.0)
    th.join(2.0)
    srv.close()
    assert got == [b"ping"]


def test_spy_dumps_both_directions(pty, caplog):
    caplog.set_level(logging.INFO, logger="cgamap.drivers.transport.spy")
    for url in (f"spy+serial://{pty.path}", f"{pty.path}?trace=1"):
        with open_transport(url, 0.5) as t:
            assert isinstance(t, SpyTransport)
            t.write(b"\x02\x00AB")
            assert pty.read(10, 1.0) == b"\x02\x00AB"
            pty.write(b"\x06")
            assert t.read(1) == b"\x06"
    text = caplog.text
    assert "TX 0000  02 00 41 42" in text and "RX 0000  06" in text
