"""The device end of a pseudo-terminal, for serial twins.

A :class:`PtyDevice` opens a pty pair, puts the slave into raw mode at once (until pyserial opens
it, the cooked line discipline would echo and translate bytes) and keeps its own slave fd open
(else reads on the master fail with EIO once the client closes).  Clients open :attr:`path`.

With ``link`` set, :attr:`path` is a symlink to the current slave: :meth:`disconnect` closes
the pair and removes the link (the client sees an unplug: reads and writes fail),
:meth:`reconnect` opens a fresh pair behind the same link (the device "returns").
:class:`LinkDevice` holds what the pty and the TCP device (``tcp_device``) share.

Baud rates: a pty accepts and ignores any rate, so bytes always pass.  The slave's termios
settings are visible from the master, so :meth:`host_baud` tells the twin the rate the client
set; a twin emulates a baud mismatch by discarding input (and garbling output) while it differs
from its own rate.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import termios
import time
import tty
from collections.abc import Callable
from typing import Self

# termios speed constants -> baud
_SPEEDS = {getattr(termios, f"B{b}"): b for b in (
    50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400, 57600,
    115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2000000,
    2500000, 3000000, 3500000, 4000000) if hasattr(termios, f"B{b}")}


class PtyClosed(OSError):
    """The pty pair is closed (disconnected) or the master failed."""


class LinkDevice:
    """The device end of a link a twin serves (a pty, a TCP port): what the kinds share.
    A subclass provides ``is_open``, ``_open`` (open the link) and ``disconnect`` (close it)."""

    is_open: bool
    _open: Callable[[], None]
    disconnect: Callable[[], None]

    def reconnect(self) -> None:
        """Open the link afresh (the device returns)."""
        if self.is_open:
            self.disconnect()
        self._open()

    def close(self) -> None:
        self.disconnect()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class PtyDevice(LinkDevice):
    """Master side of a pty pair with select-based timeouts; optional stable symlink path."""

    def __init__(self, link: str | None = None) -> None:
        self.link = link
        self.master: int | None = None
        self._slave: int | None = None
        self.slave_name = ""
        self.dropped_bytes = 0  # output discarded because nobody read it in time
        self._open()

    # -- life cycle ------------------------------------------------------------------------
    def _open(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        # the master must not echo or translate either
        tty.setraw(master)
        os.set_blocking(master, False)
        self.master, self._slave = master, slave
        self.slave_name = os.ttyname(slave)
        if self.link:
            tmp = f"{self.link}.{os.getpid()}.tmp"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self.slave_name, tmp)
            os.replace(tmp, self.link)  # atomic: the link never points nowhere while open

    @property
    def path(self) -> str:
        """What a client opens: the stable link if any, else the slave device."""
        return self.link or self.slave_name

    @property
    def is_open(self) -> bool:
        return self.master is not None

    def disconnect(self) -> None:
        """Close the pair (as a USB unplug looks to the client) and remove the link."""
        if self.link:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link)
        for fd in (self.master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self._slave = None

    # -- I/O -------------------------------------------------------------------------------
    def read(self, n: int = 4096, timeout: float = 0.1) -> bytes:
        """Up to ``n`` bytes the client wrote; b"" after ``timeout`` with none."""
        fd = self.master
        if fd is None:
            raise PtyClosed("pty is disconnected")
        ready, _, _ = select.select([fd], [], [], max(0.0, timeout))
        if not ready:
            return b""
        try:
            return os.read(fd, n)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # no slave open at the moment: nothing to read
                time.sleep(min(timeout, 0.01))
                return b""
            raise PtyClosed(str(exc)) from exc

    def write(self, data: bytes, timeout: float = 0.5) -> int:
        """Write ``data``; what the client does not drain within ``timeout`` is dropped, as on
        a real UART without flow control.  Returns the number of bytes written."""
        fd = self.master
        if fd is None:
            raise PtyClosed("pty is disconnected")
        view = memoryview(data)
        deadline = time.monotonic() + timeout
        while view:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            _, ready, _ = select.select([], [fd], [], left)
            if not ready:
                break
            try:
                view = view[os.write(fd, view):]
            except BlockingIOError:
                continue
            except OSError as exc:
                raise PtyClosed(str(exc)) from exc
        self.dropped_bytes += len(view)
        return len(data) - len(view)

    def host_baud(self) -> int | None:
        """The baud rate the client set on the slave (None if not a standard rate)."""
        fd = self.master
        if fd is None:
            return None
        try:
            speed = termios.tcgetattr(fd)[5]
        except termios.error:
            return None
        return _SPEEDS.get(speed)

    def flush_input(self) -> None:
        """Discard what the client has written so far."""
        while self.master is not None and self.read(65536, 0.0):
            pass
