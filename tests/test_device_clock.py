"""DeviceClock: scan stamps from the device's clock, so a scan read late on a busy host keeps
the instant it was taken (late stamps put the odometry guess of a moving robot off by its speed
times the lateness: ghost walls in the daemon's map under load)."""

from __future__ import annotations

import time

import numpy as np
from cgamap.drivers.device_clock import DeviceClock, WrappingCounter
from cgamap.drivers.hokuyo import HokuyoDriver
from cgamap.drivers.sim.hokuyo import HokuyoTwin

MS = 1_000_000


def arrivals(n: int, rng: np.random.Generator, offset_ns: int = 7_000 * MS,
             drift: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Device ms of scans 25 ms apart, when each was taken (host ns) and when it arrived:
    2-3 ms of transfer, and every fifth one held up to 200 ms by a busy host."""
    dev = 1000 + 25 * np.arange(n)
    taken = offset_ns + (dev * MS * (1.0 + drift)).astype(np.int64)
    delay = rng.uniform(2, 3, n) * MS
    late = rng.random(n) < 0.2
    delay[late] += rng.uniform(0, 200, late.sum()) * MS
    return dev, taken, taken + delay.astype(np.int64)


def test_late_arrivals_keep_the_instant_they_were_taken():
    dev, taken, arrived = arrivals(2000, np.random.default_rng(0))
    clock = DeviceClock()
    stamps = np.array([clock.stamp(d, a) for d, a in zip(dev, arrived, strict=True)])
    assert np.all(stamps <= arrived)
    err = (stamps - taken)[10:] / MS  # from the first few on, the least delay is in view
    late = (arrived - taken)[10:] / MS
    print(f"arrival late up to {late.max():.0f} ms; stamp error {err.min():.2f}.."
          f"{err.max():.2f} ms")
    assert late.max() > 150 and 1.9 < err.min() and err.max() < 3.1


def test_drifting_device_clock_is_followed():
    dev, taken, arrived = arrivals(40_000, np.random.default_rng(1), drift=1e-4)  # 1000 s
    clock = DeviceClock()
    err = np.array([clock.stamp(d, a) for d, a in zip(dev, arrived, strict=True)]) - taken
    assert np.abs(err[10:]).max() < 5 * MS and clock.resets == 0


def test_a_device_clock_that_starts_again_starts_a_new_estimate():
    clock = DeviceClock()
    for d in range(1000, 2000, 25):
        clock.stamp(d, 5_000 * MS + d * MS)
    assert clock.offset_ns == 5_000 * MS
    assert clock.stamp(10, 9_000 * MS) == 9_000 * MS  # back to 10 ms: powered up again
    assert clock.resets == 1 and clock.offset_ns == 9_000 * MS - 10 * MS
    # its offset jumping up by seconds (a clock that stood still) also starts again
    assert clock.stamp(35, 12_000 * MS) == 12_000 * MS and clock.resets == 2


def test_hokuyo_scans_read_late_are_stamped_when_taken(tmp_path):
    """Scans left queued for 0.3 s arrive together; their stamps stay 25 ms apart."""
    with HokuyoTwin(link=str(tmp_path / "tty")) as tw, \
            HokuyoDriver(tw.url, 0.5, command_timeout=1.0, stall_timeout=2.0) as d:
        for _ in range(12):  # let the clock see scans that came straight through
            assert d.read_scan(2.0) is not None
        time.sleep(0.3)
        scans = [d.read_scan(2.0) for _ in range(8)]
    assert all(s is not None for s in scans)
    dev = np.array([s.device_stamp for s in scans])
    stamps = np.array([s.stamp_ns for s in scans])
    assert np.all(np.diff(dev) == 25)  # UTM-30LX: a scan every 25 ms of device time
    assert np.abs(np.diff(stamps) - 25 * MS).max() < 3 * MS, np.diff(stamps) / MS


def test_wrapping_counter_unwraps_drops_wraps_and_long_gaps():
    """An 8-bit sweep counter at 75 Hz (wraps every 3.4 s) read with up to 0.5 s of jitter:
    single steps, drops of a few counts, and silences of many wraps come out right."""
    tick = 1_000_000_000 // 75
    rng = np.random.default_rng(5)
    counts = np.cumsum(rng.choice([1, 1, 1, 2, 7, 14], 3000)) + 250
    counts[1500:] += 75 * 60                           # a minute of silence
    counts[2500:] += 200                               # and a gap of 2.7 s
    arrive = counts * tick + rng.uniform(0, 0.5e9, len(counts)).astype(np.int64)
    arrive = np.maximum.accumulate(arrive)
    unwrap = WrappingCounter(8, tick)
    got = np.array([unwrap.unwrap(c % 256, a) for c, a in zip(counts, arrive, strict=True)])
    assert np.array_equal(got - got[0], counts - counts[0])
    assert unwrap.unwrap(got[-1] % 256, arrive[-1]) == got[-1]   # the same again: no step
    unwrap.reset()
    assert unwrap.unwrap(3, 0) == 3                              # afresh from the raw value
