"""The shared poll loop (drivers.pacing.paced_reads) behind ModbusBase.poll and PanTilt.poll,
on a fake clock: the slot grid, skipped slots, count, stop and the silence error."""

from __future__ import annotations

import threading

import pytest
from cgamap.drivers import pacing
from cgamap.drivers.messages import ErrorCounters


class FakeTime:
    """monotonic() and sleep() of a clock that only moves when told to."""

    def __init__(self) -> None:
        self.t = 100.0

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += max(0.0, seconds)


@pytest.fixture
def clock(monkeypatch):
    fake = FakeTime()
    monkeypatch.setattr(pacing, "time", fake)
    return fake


def reader(clock: FakeTime, durations: list[float], results: list):
    """A read that takes durations[i] and returns results[i]; records when it started."""
    calls: list[float] = []

    def read():
        i = len(calls)
        calls.append(clock.t)
        clock.t += durations[i % len(durations)]
        return results[i % len(results)]

    return read, calls


def test_reads_on_the_slot_grid_and_counts_skipped_slots(clock):
    errors = ErrorCounters()
    # slot 1's read overruns 2.5 periods: slots 2 and 3 are skipped, the grid is kept
    read, calls = reader(clock, [0.001, 0.001, 0.025, 0.001, 0.001], ["a", "b", "c", "d", "e"])
    out = list(pacing.paced_reads(read, 100.0, errors, count=5))
    assert out == ["a", "b", "c", "d", "e"]
    starts = [round((c - 100.0) * 100.0, 6) for c in calls]
    assert starts == [0.0, 1.0, 2.0, 5.0, 6.0]
    assert errors.dropped == 2


def test_failed_reads_are_not_yielded_and_count_counts_results(clock):
    errors = ErrorCounters()
    read, calls = reader(clock, [0.0], [None, 1, None, None, 2, 3])
    assert list(pacing.paced_reads(read, 10.0, errors, count=3)) == [1, 2, 3]
    assert len(calls) == 6 and errors.dropped == 0


def test_stop_ends_the_loop(clock):
    stop = threading.Event()
    n = 0

    def read():
        nonlocal n
        n += 1
        if n == 3:
            stop.set()
        return n

    # the event's wait is real: set before the wait, it returns at once
    assert list(pacing.paced_reads(read, 1000.0, ErrorCounters(), stop=stop)) == [1, 2, 3]
    assert list(pacing.paced_reads(read, 1000.0, ErrorCounters(), stop=stop)) == []


def test_silence_raises_the_given_error(clock):
    read, calls = reader(clock, [0.0], [None])
    with pytest.raises(RuntimeError, match="quiet 0.25"):
        list(pacing.paced_reads(read, 10.0, ErrorCounters(), max_silence_s=0.25,
                                silence_error=lambda s: RuntimeError(f"quiet {s:g}")))
    assert len(calls) == 4              # at 0, 0.1, 0.2 and 0.3 s: the last one is past 0.25
    with pytest.raises(TimeoutError, match="0.25 s"):
        list(pacing.paced_reads(read, 10.0, ErrorCounters(), max_silence_s=0.25))


def test_a_success_restarts_the_silence(clock):
    read, _ = reader(clock, [0.0], [None, None, 1, None, None, 2])
    # 0.25 s of silence never passes: a result comes every third slot (0.3 s apart at 10 Hz)
    assert list(pacing.paced_reads(read, 10.0, ErrorCounters(), count=2,
                                   max_silence_s=0.25)) == [1, 2]


def test_drivers_poll_through_paced_reads():
    """ModbusBase.poll and PanTilt.poll are this loop (no copy of it left in the drivers)."""
    import inspect

    from cgamap.drivers import modbus_base, pantilt

    for cls in (modbus_base.ModbusBase, pantilt.PanTilt):
        src = inspect.getsource(cls.poll)
        assert "paced_reads(" in src and "wait_next_slot" not in src
