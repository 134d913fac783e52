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


__all__ = ["DeviceClock"]
