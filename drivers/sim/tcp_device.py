"""The device end of a loopback TCP link, for twins of Ethernet devices (Hokuyo UST-xxLX,
UTM-30LX-EW: SCIP 2.0 over TCP, port 10940 on the real sensor).

Same interface as :class:`~.pty_device.PtyDevice` (``read``, ``write``, ``path``, ``is_open``,
``disconnect``, ``reconnect``, ``close``), so a twin can serve either.  One client at a time:
a new connection replaces the old one.  :meth:`disconnect` closes the listener and the client
(the client sees the peer close; new connections are refused); :meth:`reconnect` listens again
on the same port.  Output while no client is connected is lost, as on the wire.
"""

from __future__ import annotations

import contextlib
import select
import socket
import time

from .pty_device import LinkDevice, PtyClosed


class TcpDevice(LinkDevice):
    """Listening socket plus the current client, with select-based timeouts."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host, self.port = host, port
        self.listener: socket.socket | None = None
        self.client: socket.socket | None = None
        self.dropped_bytes = 0
        self._open()

    def _open(self) -> None:
        """Listen (again) on the port."""
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, self.port))
        s.listen(1)
        s.setblocking(False)
        self.port = s.getsockname()[1]       # keep the port across reconnects
        self.listener = s

    @property
    def path(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def is_open(self) -> bool:
        return self.listener is not None

    def _drop_client(self) -> None:
        if self.client is not None:
            with contextlib.suppress(OSError):
                self.client.close()
            self.client = None

    def disconnect(self) -> None:
        self._drop_client()
        if self.listener is not None:
            with contextlib.suppress(OSError):
                self.listener.close()
            self.listener = None

    def read(self, n: int = 4096, timeout: float = 0.1) -> bytes:
        """Up to ``n`` bytes from the client (accepting one if it is waiting); b"" on timeout."""
        if self.listener is None:
            raise PtyClosed("device is disconnected")
        socks = [self.listener] + ([self.client] if self.client is not None else [])
        ready, _, _ = select.select(socks, [], [], max(0.0, timeout))
        if self.listener in ready:
            with contextlib.suppress(BlockingIOError):
                conn, _ = self.listener.accept()
                conn.setblocking(False)
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._drop_client()
                self.client = conn
            return b""
        if self.client is None or self.client not in ready:
            return b""
        try:
            data = self.client.recv(n)
        except BlockingIOError:
            return b""
        except OSError:
            data = b""
        if not data:                           # the client went away
            self._drop_client()
        return data

    def write(self, data: bytes, timeout: float = 0.5) -> int:
        """Send to the client; what cannot go out within ``timeout`` (or with no client) is
        dropped.  Returns the number of bytes sent."""
        if self.listener is None:
            raise PtyClosed("device is disconnected")
        view = memoryview(data)
        deadline = time.monotonic() + timeout
        while view and self.client is not None:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            _, ready, _ = select.select([], [self.client], [], left)
            if not ready:
                break
            try:
                view = view[self.client.send(view):]
            except BlockingIOError:
                continue
            except OSError:
                self._drop_client()
        self.dropped_bytes += len(view)
        return len(data) - len(view)
