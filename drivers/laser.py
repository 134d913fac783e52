"""The common API of the 2D laser drivers (SICK LMS2xx, SICK CoLa, Hokuyo SCIP 2.0).

A driver owns one :class:`~cgamap.drivers.transport.Transport`.  Subclasses implement three
hooks; the base class does the rest (opening from a URL, loss detection, reconnecting)::

    _start()                  handshake with the device and start streaming scans
    _receive_scan(timeout)    the next complete scan, or None when none came in ``timeout``
    _stop()                   stop streaming (best effort; called before close)

Loss handling: a :class:`TransportError` from the hooks (port vanished, socket reset) or no scan
for ``stall_timeout`` seconds counts as a loss (``errors.disconnects`` or ``errors.timeout``),
the transport is closed, and :meth:`read_scan` keeps trying to reopen it every
``reconnect_interval`` seconds and to restart streaming, so streaming resumes shortly after the
device returns.  :meth:`read_scan` returns None when its own timeout passes first; the
``connected`` attribute and the ``errors`` counters tell the caller what happened.
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from collections.abc import Iterator

from .messages import ErrorCounters, LaserScan
from .transport import Transport, TransportError, open_transport

log = logging.getLogger(__name__)


class DeviceError(RuntimeError):
    """The device answered, but not as the protocol says (NAK, error status, bad reply)."""


class LaserDriver(ABC):
    """Base class of the laser drivers; see the module docstring for the hooks."""

    #: protocol name used by the CLI (``--model``)
    model: str = "laser"
    #: baud rate to open a serial URL with when it names none
    default_baud: int | None = None

    def __init__(self, device: str | Transport, timeout: float = 0.5, *,
                 reconnect: bool = True, stall_timeout: float = 1.0,
                 reconnect_interval: float = 0.1) -> None:
        if isinstance(device, Transport):
            self.transport: Transport | None = device
            self.url = device.url
        else:
            self.transport = None
            self.url = device
        self.timeout = timeout
        self.reconnect = reconnect
        self.stall_timeout = stall_timeout
        self.reconnect_interval = reconnect_interval
        self.errors = ErrorCounters()
        self.connected = False
        self.seq = 0
        self._last_scan_at = 0.0
        self._next_attempt = 0.0

    # -- hooks ---------------------------------------------------------------------------
    @abstractmethod
    def _start(self) -> None:
        """Handshake and start streaming; raise TransportError or DeviceError on failure."""

    @abstractmethod
    def _receive_scan(self, timeout: float) -> LaserScan | None:
        """The next full scan (``seq`` and ``errors`` are filled in by the base class)."""

    def _stop(self) -> None:  # noqa: B027 - optional hook, a no-op by default
        """Stop streaming (best effort)."""

    # -- public API ------------------------------------------------------------------------
    def open(self) -> None:
        """Open the transport and start streaming; raises TransportError/DeviceError."""
        if self.transport is None or self.transport.closed:
            self.transport = open_transport(self.url, self.timeout, baud=self.default_baud)
        try:
            self._start()
        except BaseException:
            self._drop_transport()
            raise
        self.connected = True
        self._last_scan_at = time.monotonic()

    def close(self) -> None:
        if self.transport is not None and not self.transport.closed:
            try:
                self._stop()
            except (TransportError, DeviceError, OSError):
                pass
        self._drop_transport()

    def read_scan(self, timeout: float | None = None) -> LaserScan | None:
        """The next full scan, or None if none arrived within ``timeout`` (default 1 s)."""
        deadline = time.monotonic() + (1.0 if timeout is None else timeout)
        while True:
            now = time.monotonic()
            left = deadline - now
            if not self.connected:
                if not self.reconnect and self._last_scan_at:
                    raise TransportError(f"{self.url}: device lost")
                if now >= self._next_attempt:
                    self._next_attempt = now + self.reconnect_interval
                    try:
                        self.open()
                        log.warning("%s: streaming again", self.url)
                        continue
                    except (TransportError, DeviceError, OSError) as exc:
                        log.debug("%s: reconnect failed: %s", self.url, exc)
                if left <= 0:
                    return None
                time.sleep(min(left, max(0.0, self._next_attempt - time.monotonic()), 0.05))
                continue
            if left <= 0:
                return None
            try:
                scan = self._receive_scan(min(left, self.stall_timeout))
            except TransportError as exc:
                self.errors.disconnects += 1
                log.warning("%s: device lost (%s); reconnecting", self.url, exc)
                self._lose()
                continue
            if scan is not None:
                self._last_scan_at = time.monotonic()
                scan.seq = self.seq
                self.seq += 1
                scan.errors = self.errors.as_dict()
                return scan
            if time.monotonic() - self._last_scan_at > self.stall_timeout:
                self.errors.timeout += 1
                log.warning("%s: no scan for %.1f s; restarting", self.url, self.stall_timeout)
                self._lose()

    def scans(self, count: int | None = None, timeout: float | None = None) -> Iterator[LaserScan]:
        """Yield scans (``count`` of them, or forever); stops early only on a read timeout."""
        n = 0
        while count is None or n < count:
            scan = self.read_scan(timeout)
            if scan is None:
                return
            n += 1
            yield scan

    def __enter__(self) -> LaserDriver:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- helpers ---------------------------------------------------------------------------
    def _lose(self) -> None:
        self.connected = False
        self._drop_transport()
        self._next_attempt = 0.0

    def _drop_transport(self) -> None:
        self.connected = False
        if self.transport is not None:
            try:
                self.transport.close()
            except OSError:
                pass
        # keep a caller-supplied transport object only while it is usable
        if self.transport is not None and self.transport.closed:
            self.transport = None
