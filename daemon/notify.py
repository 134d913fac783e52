"""sd_notify written directly: one AF_UNIX datagram of ``KEY=VALUE`` lines to $NOTIFY_SOCKET.

The protocol is declared stable by systemd; a leading ``@`` in the address means the Linux
abstract namespace (a NUL byte).  Not under systemd (no $NOTIFY_SOCKET) every call is a no-op.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager


def _address() -> str | None:
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return None
    if addr.startswith("@"):
        return "\0" + addr[1:]
    if addr.startswith("/"):
        return addr
    return None  # vsock and other forms are not used by a local service


def notify(*fields: str) -> bool:
    """Send ``fields`` (e.g. ``"READY=1"``, ``"STATUS=mapping"``); True if a datagram left."""
    addr = _address()
    if addr is None:
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
            s.sendto("\n".join(fields).encode(), addr)
        return True
    except OSError:
        return False  # the manager went away: never take the daemon down for it


def ready(status: str = "") -> bool:
    return notify("READY=1", *([f"STATUS={status}"] if status else []))


def status(text: str) -> bool:
    return notify(f"STATUS={text}")


def watchdog() -> bool:
    return notify("WATCHDOG=1")


def stopping() -> bool:
    return notify("STOPPING=1")


def reloading() -> bool:
    return notify("RELOADING=1")


def watchdog_period() -> float | None:
    """Seconds between pings (half of WatchdogSec), or None when no watchdog is asked for."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec:
        return None
    if pid and pid.isdigit() and int(pid) != os.getpid():
        return None
    try:
        return max(int(usec) / 2e6, 0.01)
    except ValueError:
        return None


@contextmanager
def extending(step: float = 20.0) -> Iterator[None]:
    """While the block runs, ask the manager every ``step`` / 4 seconds for ``step`` more
    seconds (``EXTEND_TIMEOUT_USEC``, systemd 236 and later; older ones ignore it): the first
    start after an install or upgrade compiles the mapper's kernels, which takes about 30 s on
    a 2-core machine and more on a slower one, and must not look like a start that hangs
    (``TimeoutStartSec``).  A start that really hangs stops asking and times out as before.
    Not under systemd, nothing is sent."""
    if _address() is None:
        yield
        return
    done = threading.Event()

    def ask() -> None:
        while not done.is_set():
            notify(f"EXTEND_TIMEOUT_USEC={int(step * 1e6)}")
            done.wait(step / 4)

    t = threading.Thread(target=ask, name="sd-extend-timeout", daemon=True)
    t.start()
    try:
        yield
    finally:
        done.set()
        t.join()
