"""Polling on a fixed grid of absolute deadlines, shared by the polled drivers (Modbus base,
pan-tilt): slot ``k`` starts at ``t0 + k * period``; a read that overruns whole slots skips
them (counted as ``dropped``) instead of letting the schedule drift.  :func:`paced_reads` is
the drivers' ``poll`` loop on that grid."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from .messages import ErrorCounters

T = TypeVar("T")


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


def paced_reads(read: Callable[[], T | None], rate_hz: float, errors: ErrorCounters, *,
                count: int | None = None, stop: Any | None = None,
                max_silence_s: float | None = None,
                silence_error: Callable[[float], Exception] | None = None) -> Iterator[T]:
    """Call ``read`` on the slot grid of ``rate_hz`` and yield every result that is not None.

    Ends after ``count`` results or when ``stop`` (a threading.Event) is set.  With
    ``max_silence_s``, raises ``silence_error(max_silence_s)`` (default a TimeoutError) once no
    read succeeded for that long.  Failed reads are the driver's to count in ``errors``; slots
    skipped because a read overran are counted here (``dropped``).
    """
    period = 1.0 / rate_hz
    t0 = last_ok = time.monotonic()
    k = got = 0
    while count is None or got < count:
        if stop is not None and stop.is_set():
            return
        msg = read()
        now = time.monotonic()
        if msg is not None:
            got += 1
            last_ok = now
            yield msg
        elif max_silence_s is not None and now - last_ok > max_silence_s:
            if silence_error is not None:
                raise silence_error(max_silence_s)
            raise TimeoutError(f"no successful read for {max_silence_s:g} s")
        k = wait_next_slot(t0, period, k, errors, stop)
