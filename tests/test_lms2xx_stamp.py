"""SICK LMS2xx scan stamps: the instant the (last) sweep ended, not when the host finished
reading the telegram (the daemon interpolates odometry at the stamp, so a late stamp moves every
scan by speed x lateness).  Byte level (first-byte arrival, wire-time bound, counter unwrap)
and the real driver on a pty against a twin that records when each sweep ended."""

from __future__ import annotations

import time

import numpy as np
import pytest
from cgamap.drivers.lms2xx import (
    SWEEP_NS,
    Event,
    FrameParser,
    Lms2xxDriver,
    telegram_start_ns,
    wire_ns,
)
from cgamap.drivers.sim.lms2xx import Lms2xxTwin, telegram
from cgamap.drivers.sim.world import NoiseModel
from helpers_lasers import read_until

MS = 1_000_000


def _b0(values: int, rt: int | None = None) -> bytes:
    """A B0 payload of ``values`` ranges of 1 m (cm units), with a real-time index byte."""
    out = b"\xB0" + values.to_bytes(2, "little") + (100).to_bytes(2, "little") * values
    return out + (bytes([rt & 0xFF]) if rt is not None else b"") + b"\x10"


# -- byte level -------------------------------------------------------------------------------
def test_parser_keeps_the_first_byte_arrival_and_size():
    bad = bytearray(telegram(b"\xA0\x00\x10"))
    bad[5] ^= 0x01
    good = telegram(_b0(181))
    stream = b"\x33\x02" + bytes(bad) + good
    cut = len(stream) - len(good) + 1          # the good telegram's STX ends chunk 1
    chunks = [stream[:cut], stream[cut:cut + 300], stream[cut + 300:]]
    p = FrameParser()
    events = []
    for i, c in enumerate(chunks):
        events += p.feed(c, stamp_ns=(i + 1) * 100 * MS)
    (ev,) = [e for e in events if e.kind == "frame"]
    assert ev.first_ns == 100 * MS and ev.stamp_ns == 300 * MS and ev.size == len(good)
    assert p.errors.checksum == 1
    # the next telegram starts in the last chunk: its own first byte's stamp, not an old one
    ev2 = p.feed(good[:10], 400 * MS) + p.feed(good[10:], 500 * MS)
    assert [(e.first_ns, e.stamp_ns) for e in ev2] == [(400 * MS, 500 * MS)]


def test_telegram_start_is_bounded_by_the_wire_time():
    ev = Event("frame", b"", stamp_ns=1000 * MS, first_ns=1000 * MS, size=732)
    assert wire_ns(732, 38400) == pytest.approx(190.6 * MS, rel=1e-3)
    assert telegram_start_ns(ev) == 1000 * MS                         # no baud: as read
    assert telegram_start_ns(ev, 38400) == 1000 * MS - wire_ns(731, 38400)
    ev.first_ns = 700 * MS                                             # STX read early
    assert telegram_start_ns(ev, 38400) == 700 * MS
    assert telegram_start_ns(Event("frame", b"", 5, None, 8)) == 5     # made-up event


def test_sweep_counter_stamps_survive_late_reads_drops_and_wraps():
    """The driver's stamping alone: sweeps at 75 Hz from count 200 (wraps at 256), every
    sweep sent except a dropped one, a few read late in bursts, one after a 5 s silence."""
    drv = Lms2xxDriver("/dev/null", 0.5)                 # not opened: no transport, no wire
    rng = np.random.default_rng(4)
    sweeps = np.concatenate([np.arange(200, 300), np.arange(301, 400), [775, 776]])
    end = 10_000 * MS + (sweeps - 200) * SWEEP_NS
    arrive = end + 1 * MS + rng.uniform(0, 0.5, len(sweeps)) * MS
    late = rng.random(len(sweeps)) < 0.3
    late[-2:] = False                                    # after the silence: straight through
    arrive[late] += rng.uniform(0, 120, late.sum()) * MS
    arrive = np.maximum.accumulate(arrive)               # read in order
    scans = [drv._scan_from(Event("frame", _b0(181, int(j)), int(a), int(a), 373))
             for j, a in zip(sweeps, arrive, strict=True)]
    dev = np.array([s.device_stamp for s in scans])
    assert np.array_equal(dev, sweeps)                   # unwrapped through 3 wraps and a gap
    err = (np.array([s.stamp_ns for s in scans]) - end)[10:] / MS
    lag = (arrive - end)[10:] / MS
    print(f"arrival lag up to {lag.max():.0f} ms; stamp error {err.min():.2f}..{err.max():.2f}")
    assert lag.max() > 100 and err.min() >= 0.9 and err.max() < 1.6


# -- the driver against the twin on a pty -------------------------------------------------------
def _counts(scan) -> bytes:
    return np.where(np.isnan(scan.ranges), 8191, np.rint(scan.ranges / 0.01)) \
        .astype("<u2").tobytes()


def _measured(twin: Lms2xxTwin, scans: list) -> list[tuple[int, int]]:
    """For each scan, the twin's (sweep count, end ns) of the telegram with its values (once
    the twin stopped: it records a telegram just after writing it)."""
    index = {v: i for i, (v, _) in enumerate(twin.sent)}
    measured = list(twin.measured)
    return [measured[index[_counts(s)]] for s in scans]


def _twin(tmp_path, **kw) -> Lms2xxTwin:
    return Lms2xxTwin("corridor", link=str(tmp_path / "ttyLMS"), seed=2,
                      noise=NoiseModel(sigma=0.01, dropout=0.0), **kw)


def test_paced_38400_line_stamps_the_sweep_not_the_last_byte(tmp_path):
    """At 38400 baud a 181-value telegram is 97 ms on the wire: the last byte (the old stamp)
    is that late at least; the stamp from the first byte is within a sweep or so."""
    with _twin(tmp_path, pace_output=True) as tw, \
            Lms2xxDriver(tw.path, 0.5, session_baud=38400, wire_time=True) as drv:
        scans, arrivals = [], []
        for _ in range(12):
            scans.append(drv.read_scan(3.0))
            arrivals.append(drv.arrival_ns)
        assert all(s is not None for s in scans)
    ends = np.array([e for _, e in _measured(tw, scans)])
    wire = wire_ns(6 + 3 + 2 * 181 + 1, 38400) / MS
    err = (np.array([s.stamp_ns for s in scans]) - ends) / MS
    lag = (np.array(arrivals) - ends) / MS
    print(f"wire {wire:.0f} ms; last-byte lag {np.median(lag):.1f} ms (min {lag.min():.1f}); "
          f"stamp error {np.median(err):.1f} ms ({err.min():.1f}..{err.max():.1f})")
    assert lag.min() > 0.95 * wire                  # the old stamp: late by the wire time
    # the first byte came the wire time of the others before the last one was read
    stamps = np.array([s.stamp_ns for s in scans])
    assert np.all(stamps <= np.array(arrivals) - wire_ns(6 + 3 + 2 * 181, 38400))
    assert err.min() > -1.0                          # never before the sweep ended
    # the LMS sends the latest sweep once the line is free: up to one sweep (13 ms) old
    assert np.median(err) < 0.25 * wire


def test_scans_read_late_keep_their_sweep_instant(tmp_path):
    """Real-time indices through the DeviceClock: a host that stalls 100 ms every tenth read
    gets telegrams late in bursts; their stamps stay at the sweeps."""
    with _twin(tmp_path) as tw, \
            Lms2xxDriver(tw.path, 0.5, session_baud=500000, realtime_indices=True) as drv:
        for _ in range(30):                          # the clock sees straight-through scans
            assert drv.read_scan(2.0) is not None
        scans, arrivals = [], []
        for i in range(100):
            if i % 10 == 0:
                time.sleep(0.1)
            scans.append(drv.read_scan(2.0))
            arrivals.append(drv.arrival_ns)
        assert all(s is not None for s in scans)
    measured = _measured(tw, scans)
    assert [s.device_stamp for s in scans] == [j for j, _ in measured]
    assert drv._wire_real is False                  # a pty: bytes take no wire time
    ends = np.array([e for _, e in measured])
    err = (np.array([s.stamp_ns for s in scans]) - ends) / MS
    lag = (np.array(arrivals) - ends) / MS
    print(f"arrival lag median {np.median(lag):.1f} ms, max {lag.max():.1f} ms; stamp error "
          f"median {np.median(err):.2f} ms, p95 {np.percentile(err, 95):.2f} ms")
    assert lag.max() > 60 and np.median(lag) > 15   # the old stamps: late in bursts
    assert err.min() > -1.0 and np.median(err) < 8 and np.percentile(err, 95) < 25


def test_dropped_sweep_and_counter_wrap_are_stamped_right(tmp_path):
    """A truncated telegram drops a sweep (the count jumps by 2); the 8-bit index wraps
    (the twin starts counting at 181: a wrap a second after power-on, then every 3.4 s)."""
    with _twin(tmp_path, first_sweep=181) as tw, \
            Lms2xxDriver(tw.path, 0.5, session_baud=500000, realtime_indices=True) as drv:
        scans = [drv.read_scan(2.0) for _ in range(20)]
        tw.truncate(1)
        deadline = time.monotonic() + 6.0
        while time.monotonic() < deadline:
            scans.append(drv.read_scan(2.0))
            wrapped = any(b.device_stamp % 256 < a.device_stamp % 256
                          for a, b in zip(scans, scans[1:], strict=False))
            if len(scans) > 40 and wrapped:
                break
        scans += [drv.read_scan(2.0) for _ in range(10)]
        assert all(s is not None for s in scans)
    measured = _measured(tw, scans)
    dev = np.array([s.device_stamp for s in scans])
    sweeps = np.array([j for j, _ in measured])
    assert np.all(dev % 256 == sweeps % 256) and len(set(sweeps - dev)) == 1
    steps = np.diff(dev)
    assert 2 in steps and np.all(steps >= 1)            # the dropped sweep
    assert np.any(np.diff(dev % 256) < 0)               # a wrap of the wire byte
    err = (np.array([s.stamp_ns for s in scans]) - np.array([e for _, e in measured])) / MS
    after = np.flatnonzero((steps == 2) | (np.diff(dev % 256) < 0)) + 1
    print(f"stamp error {np.median(err):.2f} ms ({err.min():.2f}..{err.max():.2f}); "
          f"after the drop/wrap {err[after].round(2).tolist()}")
    assert err[10:].min() > -1.0 and np.median(err[10:]) < 8
    assert np.all(np.abs(err[after]) < 25)


def test_reconnect_starts_the_sweep_clock_afresh(tmp_path):
    """A replugged LMS powers up counting from 0 again: the driver's counter and clock start
    afresh, so the stamps stay at the sweeps."""
    with _twin(tmp_path) as tw, \
            Lms2xxDriver(tw.path, 0.5, session_baud=500000, realtime_indices=True,
                         stall_timeout=0.5) as drv:
        before = [drv.read_scan(2.0) for _ in range(40)]
        tw.unplug()
        read_until(drv, lambda: drv.errors.disconnects > 0, 3.0, 0.2)
        time.sleep(0.5)                                 # the old count runs on meanwhile
        tw.replug()
        after = [drv.read_scan(5.0) for _ in range(40)]
        assert all(s is not None for s in before + after) and drv.errors.disconnects >= 1
    measured = _measured(tw, after)
    dev = [s.device_stamp for s in after]
    assert dev == [j for j, _ in measured]             # counted afresh from the new 0
    assert drv.clock.resets == 0                       # reset by the reconnect, not guessed
    err = (np.array([s.stamp_ns for s in after]) - np.array([e for _, e in measured])) / MS
    print(f"after the replug: stamp error {np.median(err):.2f} ms "
          f"({err.min():.2f}..{err.max():.2f})")
    assert err.min() > -1.0 and np.median(err) < 8
