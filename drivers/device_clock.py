"""Host time of a device's own clock readings, estimated from when its messages arrive.

A message taken at device time ``d`` arrives at host time ``a = d * unit + offset + delay``:
``offset`` is how the two clocks stand, ``delay`` (never negative) the transfer plus whatever
the host adds -- a busy host reads a message late, never early.  The least ``a - d * unit``
over the messages of the last few seconds is therefore the offset plus the least delay, and
``d * unit`` plus that is when the message was taken, to within the least delay: a message
read late keeps the instant it was taken, where its arrival time would carry the lateness into
everything interpolated at it (odometry at a scan's stamp).
"""

from __future__ import annotations

import math
from collections import deque


class DeviceClock:
    """Sliding-window minimum of ``arrival - device time``; :meth:`stamp` per message.

    ``unit_ns``: nanoseconds per device clock tick (1 ms for SCIP timestamps).  ``window``:
    device ticks the minimum is taken over -- short enough that the two clocks' drift (about
    1e-4) stays under a tick, long enough to hold a message that came straight through.  A
    device clock that runs backwards (reset, power cycle) or whose offset rises by more than
    ``max_rise_ns`` at once (set forward on the host's side of things) starts a new estimate.
    """

    def __init__(self, unit_ns: int = 1_000_000, window: int = 10_000,
                 max_rise_ns: int = 1_000_000_000):
        self.unit_ns, self.window, self.max_rise_ns = int(unit_ns), int(window), int(max_rise_ns)
        self._min: deque[tuple[int, int]] = deque()  # (device time, offset), offsets rising
        self._last: int | None = None
        self.resets = 0

    def reset(self) -> None:
        self._min.clear()
        self._last = None

    @property
    def offset_ns(self) -> int | None:
        """The current estimate of the offset plus the least delay (None before a message)."""
        return self._min[0][1] if self._min else None

    def stamp(self, device: int, arrival_ns: int) -> int:
        """Host monotonic ns at which the message with device time ``device`` was taken
        (never later than its ``arrival_ns``)."""
        device = int(device)
        off = int(arrival_ns) - device * self.unit_ns
        if self._last is not None and (device < self._last
                                       or off - self._min[0][1] > self.max_rise_ns):
            self.reset()
            self.resets += 1
        self._last = device
        while self._min and self._min[-1][1] >= off:
            self._min.pop()
        self._min.append((device, off))
        while self._min[0][0] < device - self.window:
            self._min.popleft()
        return device * self.unit_ns + self._min[0][1]


class WrappingCounter:
    """Unwraps a ``bits``-bit device counter that advances about once per ``tick_ns`` of host
    time (a laser's sweep counter): of the counts congruent to the new value, the one nearest
    to what the host time since the previous value predicts.  Gaps of any length unwrap right
    as long as the host-time guess is off by less than half a wrap (for an 8-bit sweep counter
    at 75 Hz: 1.7 s of arrival jitter or rate error), and the count never runs backwards.
    """

    def __init__(self, bits: int, tick_ns: int) -> None:
        self.modulus, self.tick_ns = 1 << int(bits), int(tick_ns)
        self._last: tuple[int, int] | None = None  # (count, arrival ns)

    def reset(self) -> None:
        self._last = None

    def unwrap(self, value: int, arrival_ns: int) -> int:
        """The count of ``value`` (taken mod 2**bits) that arrived at host ns ``arrival_ns``."""
        value, arrival_ns = int(value) % self.modulus, int(arrival_ns)
        if self._last is None:
            count = value
        else:
            last, last_ns = self._last
            step = (value - last) % self.modulus
            expected = (arrival_ns - last_ns) / self.tick_ns
            count = last + step + self.modulus * max(0, math.floor(
                (expected - step) / self.modulus + 0.5))
        self._last = (count, arrival_ns)
        return count


__all__ = ["DeviceClock", "WrappingCounter"]
