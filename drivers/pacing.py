"""Polling on a fixed grid of absolute deadlines, shared by the polled drivers (Modbus base,
pan-tilt): slot ``k`` starts at ``t0 + k * period``; a read that overruns whole slots skips
them (counted as ``dropped``) instead of letting the schedule drift."""

from __future__ import annotations

import math
import time
from typing import Any

from .messages import ErrorCounters


def wait_next_slot(t0: float, period: float, k: int, errors: ErrorCounters,
                   stop: Any | None = None) -> int:
    """After the read of slot ``k``: the index of the next slot, waited for.

    Slots the read overran are skipped and added to ``errors.dropped``; the wait is
    ``stop.wait`` (a threading.Event, so a stop ends it early) or a sleep.
    """
    k += 1
    late = math.floor((time.monotonic() - t0) / period) - k + 1
    if late > 0:
        errors.dropped += late
        k += late
    delay = t0 + k * period - time.monotonic()
    if delay > 0:
        if stop is not None:
            stop.wait(delay)
        else:
            time.sleep(delay)
    return k
