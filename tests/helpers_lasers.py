"""Helpers shared by the laser driver tests (LMS2xx, CoLa) against their twins."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def read_until(drv: Any, done: Callable[[], bool], seconds: float, read_timeout: float) -> None:
    """Read (and drop) scans from ``drv`` until ``done()`` or ``seconds`` have passed; the
    caller asserts on the outcome."""
    deadline = time.monotonic() + seconds
    while not done() and time.monotonic() < deadline:
        drv.read_scan(read_timeout)
