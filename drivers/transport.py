"""Byte transports opened from a URL string, in the manner of pyserial's ``serial_for_url``, and
the one parser of device URLs that every driver uses (:func:`parse_device_url`).

URLs understood by :func:`open_transport`:

- ``serial:///dev/ttyUSB0?baud=500000`` or a plain device path ``/dev/ttyUSB0``.  The default
  baud is 9600 (the SICK LMS2xx power-on rate; drivers that probe or switch rates call
  :meth:`Transport.set_baud` themselves).  Options: ``baud`` (or ``baudrate``), ``exclusive=1``
  (flock).
- ``tcp://host:port`` (``socket://host:port`` and a bare ``host:port`` are accepted too).
- ``spy+<url>`` or ``<url>?trace=1``: a tracing wrapper that hex-dumps both directions to the
  ``cgamap.drivers.transport.spy`` logger at INFO level (``cgamap -v``).

Every read honours a timeout (select-based or pyserial's own); nothing busy-waits.  Failures to
open, and a device that vanishes (USB unplug, pty closed, socket reset), raise
:class:`TransportError`, a subclass of :class:`OSError`.
"""

from __future__ import annotations

import logging
import re
import select
import socket
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from urllib.parse import parse_qs, urlsplit

import serial

log = logging.getLogger(__name__)
spy_log = logging.getLogger(__name__ + ".spy")

DEFAULT_BAUD = 9600


class TransportError(OSError):
    """The transport could not be opened, or the device behind it vanished."""


class Transport:
    """A bidirectional byte stream with timeouts.

    Subclasses implement ``_raw_read(n, timeout)`` (returns b"" on timeout, raises
    TransportError when the peer is gone), ``write`` and ``close``; the base class keeps a small
    push-back buffer so that :meth:`read_until` never loses bytes that follow the terminator.
    """

    url: str

    def __init__(self, url: str, timeout: float) -> None:
        self.url = url
        self.timeout = float(timeout)
        self._buf = bytearray()
        self.closed = False

    # -- to implement -------------------------------------------------------------------
    def _raw_read(self, n: int, timeout: float) -> bytes:
        raise NotImplementedError

    def write(self, data: bytes) -> int:
        raise NotImplementedError

    def close(self) -> None:
        self.closed = True

    # -- common ------------------------------------------------------------------------
    def read(self, n: int, timeout: float | None = None) -> bytes:
        """Up to ``n`` bytes: whatever is available once the first byte arrives; b"" on timeout."""
        if n <= 0:
            return b""
        if self._buf:
            out = bytes(self._buf[:n])
            del self._buf[:n]
            return out
        return self._raw_read(n, self.timeout if timeout is None else timeout)

    def read_exactly(self, n: int, timeout: float | None = None) -> bytes:
        """Exactly ``n`` bytes, or fewer if the (overall) timeout passes first."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        out = bytearray()
        while len(out) < n:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            chunk = self.read(n - len(out), left)
            if not chunk:
                break
            out += chunk
        return bytes(out)

    def read_until(self, terminator: bytes = b"\n", max_bytes: int = 65536,
                   timeout: float | None = None) -> bytes:
        """Bytes up to and including ``terminator``; on timeout or ``max_bytes`` whatever came."""
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        out = bytearray()
        while True:
            idx = out.find(terminator)
            if idx >= 0:
                end = idx + len(terminator)
                self._buf[:0] = out[end:]
                return bytes(out[:end])
            if len(out) >= max_bytes:
                self._buf[:0] = out[max_bytes:]
                return bytes(out[:max_bytes])
            left = deadline - time.monotonic()
            if left <= 0:
                return bytes(out)
            chunk = self.read(4096, left)
            if not chunk:
                return bytes(out)
            out += chunk

    @property
    def baud(self) -> int | None:
        """The line rate, or None when the stream is not a serial line."""
        return None

    def set_baud(self, baud: int) -> None:
        """Change the line rate (serial only; a no-op on network transports)."""

    def reset_input(self) -> None:
        """Discard everything received so far."""
        self._buf.clear()

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}>"


class SerialTransport(Transport):
    """A pyserial port (real UART, USB adapter, or the pty of a simulated device)."""

    def __init__(self, url: str, path: str, baud: int, timeout: float,
                 exclusive: bool = False) -> None:
        super().__init__(url, timeout)
        self.path = path
        try:
            self._ser = serial.Serial(path, baudrate=baud, timeout=timeout,
                                      write_timeout=max(1.0, timeout),
                                      exclusive=exclusive or None)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"cannot open serial port {path}: {exc}") from exc

    @property
    def baud(self) -> int:
        return int(self._ser.baudrate)

    def _raw_read(self, n: int, timeout: float) -> bytes:
        try:
            if self._ser.timeout != timeout:
                self._ser.timeout = timeout
            first = self._ser.read(1)
            if not first:
                return b""
            more = min(n - 1, self._ser.in_waiting)
            return first + (self._ser.read(more) if more > 0 else b"")
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError/AttributeError: pyserial after close() from another thread (fd None).
            raise TransportError(f"serial port {self.path} lost: {exc}") from exc

    def write(self, data: bytes) -> int:
        try:
            return int(self._ser.write(data) or 0)
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise TransportError(f"serial port {self.path} lost: {exc}") from exc

    def set_baud(self, baud: int) -> None:
        try:
            self._ser.baudrate = int(baud)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"serial port {self.path}: cannot set {baud} baud: {exc}") \
                from exc

    def reset_input(self) -> None:
        super().reset_input()
        try:
            self._ser.reset_input_buffer()
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise TransportError(f"serial port {self.path} lost: {exc}") from exc

    def close(self) -> None:
        super().close()
        try:
            self._ser.close()
        except (serial.SerialException, OSError):
            pass


class TcpTransport(Transport):
    """A TCP client socket; reads wait in select() with the timeout."""

    def __init__(self, url: str, host: str, port: int, timeout: float) -> None:
        super().__init__(url, timeout)
        self.host, self.port = host, port
        try:
            self._sock = socket.create_connection((host, port), timeout=max(timeout, 1.0))
        except OSError as exc:
            raise TransportError(f"cannot connect to {host}:{port}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.settimeout(None)
        self._sock.setblocking(False)

    def _raw_read(self, n: int, timeout: float) -> bytes:
        try:
            ready, _, _ = select.select([self._sock], [], [], max(0.0, timeout))
            if not ready:
                return b""
            data = self._sock.recv(n)
        except BlockingIOError:
            return b""
        except (OSError, ValueError) as exc:
            raise TransportError(f"connection to {self.host}:{self.port} lost: {exc}") from exc
        if not data:
            raise TransportError(f"connection to {self.host}:{self.port} closed by peer")
        return data

    def write(self, data: bytes) -> int:
        view = memoryview(data)
        deadline = time.monotonic() + max(1.0, self.timeout)
        try:
            while view:
                _, ready, _ = select.select([], [self._sock], [], max(0.0,
                                           deadline - time.monotonic()))
                if not ready:
                    raise TransportError(f"write to {self.host}:{self.port} timed out")
                sent = self._sock.send(view)
                view = view[sent:]
        except TransportError:
            raise
        except (OSError, ValueError) as exc:
            raise TransportError(f"connection to {self.host}:{self.port} lost: {exc}") from exc
        return len(data)

    def reset_input(self) -> None:
        super().reset_input()
        for _ in range(64):  # bounded: a peer that streams fast must not keep us here
            if not self._raw_read(65536, 0.0):
                break

    def close(self) -> None:
        super().close()
        try:
            self._sock.close()
        except OSError:
            pass


class SpyTransport(Transport):
    """Wraps another transport and hex-dumps every byte read and written to the log."""

    def __init__(self, inner: Transport) -> None:
        super().__init__("spy+" + inner.url, inner.timeout)
        self.inner = inner

    @staticmethod
    def _dump(direction: str, data: bytes) -> None:
        if data and spy_log.isEnabledFor(logging.INFO):
            for i in range(0, len(data), 32):
                chunk = data[i:i + 32]
                text = "".join(chr(b) if 32 <= b < 127 else "." for b in chunk)
                spy_log.info("%s %04x  %s  %s", direction, i, chunk.hex(" "), text)

    def _raw_read(self, n: int, timeout: float) -> bytes:
        data = self.inner.read(n, timeout)
        self._dump("RX", data)
        return data

    def write(self, data: bytes) -> int:
        self._dump("TX", data)
        return self.inner.write(data)

    @property
    def baud(self) -> int | None:
        return self.inner.baud

    def set_baud(self, baud: int) -> None:
        spy_log.info("-- baud %d", baud)
        self.inner.set_baud(baud)

    def reset_input(self) -> None:
        super().reset_input()
        self.inner.reset_input()

    def close(self) -> None:
        super().close()
        self.inner.close()

    @property
    def timeout(self) -> float:  # type: ignore[override]
        return self.inner.timeout if hasattr(self, "inner") else self._timeout

    @timeout.setter
    def timeout(self, value: float) -> None:
        self._timeout = value
        if hasattr(self, "inner"):
            self.inner.timeout = value


# -- device URLs -------------------------------------------------------------------------------

#: schemes whose URL names a network peer (``scheme://host:port``)
NETWORK_SCHEMES = frozenset({"tcp", "socket", "modbus+tcp", "rtu+tcp"})
#: schemes whose URL names a local device path (``scheme:///dev/ttyUSB0``)
PATH_SCHEMES = frozenset({"serial", "rtu"})
# a bare host:port (as `cgamap sim-device` prints for TCP twins), taken as tcp://host:port
_BARE_HOST_PORT = re.compile(r"[\w.\-]+:\d+(\?.*)?")


class DeviceUrlError(ValueError):
    """A device URL that cannot name a device (one line: the URL and what is wrong)."""


@dataclass(frozen=True)
class DeviceUrl:
    """A device URL taken apart by :func:`parse_device_url`.

    ``url`` is the URL without its ``spy+`` prefix; ``scheme`` is lower case, ``"serial"`` for a
    plain device path.  ``path`` is the device path of the path schemes; for a scheme the parser
    does not know (a pyserial handler such as ``loop://``) it is the URL without its query.
    ``host``/``port`` are set for the network schemes.  ``baud`` comes from ``baudrate=`` (or
    ``baud=``); ``options`` holds the other query options (the last value of each);
    ``spy`` is set by a ``spy+`` prefix or ``trace=1``.
    """

    url: str
    scheme: str
    path: str = ""
    host: str = ""
    port: int | None = None
    baud: int | None = None
    options: Mapping[str, str] = field(default_factory=dict, hash=False)
    spy: bool = False

    @property
    def is_network(self) -> bool:
        return self.scheme in NETWORK_SCHEMES

    @property
    def address(self) -> str:
        """``host:port`` (IPv6 hosts in brackets)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{host}:{self.port}"


def _flag(value: str) -> bool:
    return value.lower() in ("1", "true", "yes", "on")


def _forms(schemes: Collection[str]) -> str:
    """The accepted URL forms, for an error message."""
    forms = ["a device path"] if "serial" in schemes else []
    forms += [f"{s}://host:port" if s in NETWORK_SCHEMES else f"{s}://" for s in schemes]
    return ", ".join(forms[:-1]) + " or " + forms[-1] if len(forms) > 1 else "".join(forms)


def parse_device_url(url: str, schemes: Collection[str] | None = None,
                     error: Callable[[str], Exception] = DeviceUrlError) -> DeviceUrl:
    """Take a device URL apart: ``[spy+]scheme://…?options``, a plain device path, or a bare
    ``host:port`` (read as ``tcp://host:port``).

    ``schemes`` limits the accepted schemes (``"serial"`` also admits a plain path); ``error``
    is the exception class raised, with a one-line message naming the URL, for an unaccepted
    scheme, a network URL without host or numeric port, a path scheme without a path, or a
    ``baud``/``baudrate`` that is not a positive whole number.
    """
    if not url or not url.strip():
        raise error("empty device URL")
    rest, spy = url, False
    while rest.startswith("spy+"):
        rest, spy = rest[4:], True
    if "://" not in rest and _BARE_HOST_PORT.fullmatch(rest):
        rest = "tcp://" + rest
    if "://" in rest:
        parts = urlsplit(rest)
        scheme, query = parts.scheme.lower(), parts.query
    else:                                   # a plain device path, maybe with ?options
        parts, scheme = None, "serial"
        query = rest.partition("?")[2]
    if schemes is not None and scheme not in schemes:
        raise error(f"{url}: unknown URL scheme {scheme + '://'!r} (an unsupported scheme for "
                    f"this device: use {_forms(schemes)})")
    kw: dict = {}
    if parts is None:
        kw["path"] = rest.partition("?")[0]
    elif scheme in NETWORK_SCHEMES:
        try:
            port = parts.port
        except ValueError as exc:           # a non-numeric or out-of-range port
            raise error(f"{url}: malformed URL ({exc}); {scheme}:// needs host:port") from None
        if not parts.hostname or not port:
            raise error(f"{url}: {scheme}:// needs host:port (e.g. {scheme}://127.0.0.1:4001)")
        kw.update(host=parts.hostname, port=port)
    elif scheme in PATH_SCHEMES:
        # serial:///dev/x is the form; serial://dev/x means the same
        kw["path"] = "/" + parts.netloc + parts.path if parts.netloc else parts.path
        if not kw["path"]:
            raise error(f"{url}: {scheme}:// needs a device path ({scheme}:///dev/ttyUSB0)")
    else:                                   # a handler the caller passes on (pyserial's loop://)
        kw["path"] = rest.partition("?")[0]
    options = {k: v[-1] for k, v in parse_qs(query).items()}
    spy = _flag(options.pop("trace", "0")) or spy
    bauds = [options.pop(k) for k in ("baudrate", "baud") if k in options]   # baudrate wins
    if bauds:
        raw = bauds[0]
        try:
            kw["baud"] = int(raw)
        except ValueError:
            raise error(f"{url}: baud rate {raw!r} is not a whole number") from None
        if kw["baud"] <= 0:
            raise error(f"{url}: baud rate {kw['baud']} must be positive")
    return DeviceUrl(rest, scheme, options=MappingProxyType(options), spy=spy, **kw)


# -- opening a transport -------------------------------------------------------------------

TRANSPORT_SCHEMES = ("serial", "tcp", "socket")


def open_transport(url: str, timeout: float = 0.5, baud: int | None = None) -> Transport:
    """Open the byte stream named by ``url`` (see the module docstring for the forms).

    ``baud`` is the rate used when the URL gives none (default 9600).
    """
    if url.startswith("spy://"):            # an older spelling of spy+
        url = "spy+" + url[6:]
    u = parse_device_url(url, TRANSPORT_SCHEMES, TransportError)
    options = dict(u.options)
    if u.is_network:
        tr: Transport = TcpTransport(u.url, u.host, u.port, timeout)
    else:
        exclusive = _flag(options.pop("exclusive", "0"))
        tr = SerialTransport(u.url, u.path, u.baud or baud or DEFAULT_BAUD, timeout, exclusive)
    if options:
        log.warning("%s: ignoring unknown options %s", url, ", ".join(sorted(options)))
    return SpyTransport(tr) if u.spy else tr
