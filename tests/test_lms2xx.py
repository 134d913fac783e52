"""SICK LMS2xx: byte-level vectors, the pure parser (incl. fuzzing), and the real driver on a
real pyserial port against the twin on a pty (init, streaming, stop, every fault)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from cgamap.drivers.laser import DeviceError
from cgamap.drivers.lms2xx import (
    FrameError,
    FrameParser,
    Lms2xxDriver,
    ScanAssembler,
    crc16_sick,
    decode_b0,
    frame,
)
from cgamap.drivers.messages import ErrorCounters, LaserScan
from cgamap.drivers.sim.lms2xx import Lms2xxTwin, sick_crc, telegram
from cgamap.drivers.sim.world import NoiseModel
from helpers_lasers import read_until
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

FUZZ_EXAMPLES = int(os.environ.get("CGAMAP_FUZZ_EXAMPLES", "10000"))

VECTORS = [  # reference lasers.md §1.2, all bytes as published
    "02 00 02 00 20 24 34 08", "02 00 02 00 20 25 35 08", "02 00 02 00 20 40 50 08",
    "02 00 02 00 20 41 51 08", "02 00 02 00 20 42 52 08", "02 00 02 00 20 48 58 08",
    "02 00 01 00 31 15 12", "02 00 01 00 74 50 12", "02 00 02 00 30 01 31 18",
    "02 00 05 00 3B B4 00 32 00 3B 1F", "02 00 05 00 3B B4 00 64 00 97 49",
    "02 00 05 00 3B 64 00 64 00 1D 0F", "02 00 05 00 3B 64 00 19 00 E7 72",
    "02 80 03 00 A0 00 10 16 0A",
    "02 00 0A 00 20 00 53 49 43 4B 5F 4C 4D 53 BE C5",
]


# -- byte level -------------------------------------------------------------------------------
@pytest.mark.parametrize("hexstr", VECTORS)
def test_crc_and_framing_vectors(hexstr):
    raw = bytes.fromhex(hexstr)
    assert crc16_sick(raw[:-2]) == int.from_bytes(raw[-2:], "little")
    assert sick_crc(raw[:-2]) == int.from_bytes(raw[-2:], "little")  # the twin's own loop
    assert frame(raw[4:-2], raw[1]) == raw


def test_crc_is_not_buypass():
    assert crc16_sick(bytes.fromhex("02 00 02 00 20 24")) == 0x0834  # BUYPASS would be 0x98DB


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=1, max_size=816))
def test_table_crc_equals_reference_loop(data):
    assert crc16_sick(data) == sick_crc(data)


def test_ack_then_reply_on_the_wire():
    p = FrameParser()
    ev = p.feed(bytes.fromhex("06 02 80 03 00 A0 00 10 16 0A"))
    assert [e.kind for e in ev] == ["ack", "frame"]
    assert ev[1].payload == b"\xA0\x00\x10"
    assert p.errors.framing == 0 and p.errors.checksum == 0


def test_resync_after_garbage_and_bad_crc():
    good = telegram(b"\xA0\x00\x10")
    bad = bytearray(telegram(b"\xB2" + bytes(8) + b"\x10"))
    bad[6] ^= 0x40
    errors = ErrorCounters()
    p = FrameParser(errors)
    stream = b"\xFF\x02\x33garbage" + good + bytes(bad) + b"\x02\x80" + good
    events = []
    for i in range(0, len(stream), 3):  # byte chunks split anywhere
        events += p.feed(stream[i:i + 3])
    frames = [e.payload for e in events if e.kind == "frame"]
    assert frames == [b"\xA0\x00\x10", b"\xA0\x00\x10"]
    assert errors.checksum >= 1 and errors.framing >= 10


def b0_payload(values, unit_code=0, partial=0, rt=None, status=0x10) -> bytes:
    w = len(values) | (partial << 11) | (unit_code << 14)
    out = b"\xB0" + w.to_bytes(2, "little") + np.asarray(values, "<u2").tobytes()
    return out + (bytes([rt]) if rt is not None else b"") + bytes([status])


def test_decode_b0_units_masks_and_flags():
    s = decode_b0(b0_payload([100, 8191, 0x2000 | 250, 8183, 8182]))
    assert s.unit == 0.01 and s.range_max == pytest.approx(81.91)
    np.testing.assert_allclose(s.ranges, [1.0, np.nan, 2.5, np.nan, 81.82])
    assert s.rt_index is None and s.status == 0x10
    mm = decode_b0(b0_payload([1234, 0x8000 | 50], unit_code=1), measuring_mode=0)
    np.testing.assert_allclose(mm.ranges, [1.234, np.nan])  # mode 00 bit 15: dazzle
    m2 = decode_b0(b0_payload([1234, 0x8000 | 50], unit_code=1), measuring_mode=2)
    np.testing.assert_allclose(m2.ranges, [1.234, 0.05])    # mode 02 bit 15: field C
    refl = decode_b0(b0_payload([0x4000 | 300], unit_code=0), measuring_mode=3)
    assert refl.ranges[0] == pytest.approx(3.0) and refl.reflect[0] == 1
    m5 = decode_b0(b0_payload([20000], unit_code=1), measuring_mode=5)
    assert m5.ranges[0] == pytest.approx(20.0)
    rt = decode_b0(b0_payload([5, 6], rt=77, partial=1))
    assert rt.rt_index == 77 and rt.partial == 1
    dm = decode_b0(b0_payload([5], unit_code=2))
    assert dm.ranges[0] == pytest.approx(0.5)
    for bad in (b0_payload([1, 2])[:-2], b"\xB0\x05\x00\x10", b0_payload([1], unit_code=3),
                b"\xA0\x00\x10"):
        with pytest.raises(FrameError):
            decode_b0(bad)


def test_assembler_interleaves_partials_and_drops_broken_sets():
    asm = ScanAssembler(100, 0.25)
    full = np.arange(401) * 0.01 + 1.0
    parts = [decode_b0(b0_payload(np.rint(full[p::4] * 100), partial=p)) for p in range(4)]
    assert [asm.add(q) for q in parts[:3]] == [None, None, None]
    scan = asm.add(parts[3])
    np.testing.assert_allclose(scan.ranges, full)
    assert scan.angle_min == pytest.approx(-np.radians(50))
    assert scan.angle_increment == pytest.approx(np.radians(0.25))
    # a lost partial abandons the set; the next complete set comes through
    assert asm.add(parts[0]) is None and asm.add(parts[2]) is None
    assert asm.errors.dropped == 1
    for q in parts:
        out = asm.add(q)
    np.testing.assert_allclose(out.ranges, full)
    # a full-count telegram is a scan by itself
    asm2 = ScanAssembler(180, 0.5)
    s2 = asm2.add(decode_b0(b0_payload(np.full(361, 200))))
    assert len(s2.ranges) == 361 and np.allclose(s2.ranges, 2.0)
    half = ScanAssembler(180, 0.5)
    a = decode_b0(b0_payload(np.full(181, 100), partial=0))
    b = decode_b0(b0_payload(np.full(180, 300), partial=1))
    assert half.add(a) is None
    out = half.add(b)
    assert np.allclose(out.ranges[0::2], 1.0) and np.allclose(out.ranges[1::2], 3.0)


# -- fuzzing the pure parser ------------------------------------------------------------------
def _pipeline(stream: bytes, chunk: int) -> tuple[list[LaserScan], ErrorCounters]:
    errors = ErrorCounters()
    parser = FrameParser(errors)
    asm = ScanAssembler(100, 1.0, errors)
    scans = []
    for i in range(0, len(stream), chunk):
        for ev in parser.feed(stream[i:i + chunk], stamp_ns=0):
            if ev.kind != "frame" or ev.payload[0] != 0xB0:
                continue
            try:
                part = decode_b0(ev.payload)
            except FrameError:
                errors.framing += 1
                continue
            scan = asm.add(part)
            if scan is not None:
                scans.append(scan)
    return scans, errors


_RNG = np.random.default_rng(7)
_ORIGINALS = [b0_payload(_RNG.integers(0, 8191, 101)) for _ in range(4)]
_CLEAN = b"".join(b"\x06" + telegram(p) for p in _ORIGINALS)
_KEYS = {np.nan_to_num(decode_b0(p).ranges, nan=-1.0).tobytes() for p in _ORIGINALS}


def _mutant(rng: np.random.Generator) -> bytes:
    """One fuzz case: random bytes, a valid stream with bytes replaced/inserted/deleted, or a
    valid stream cut and spliced."""
    kind = rng.integers(0, 4)
    if kind == 0:
        return rng.integers(0, 256, rng.integers(0, 600), dtype=np.uint8).tobytes()
    arr = bytearray(_CLEAN)
    if kind == 1:
        for pos in rng.integers(0, len(arr), rng.integers(1, 7)):
            arr[pos] = int(rng.integers(0, 256))
    elif kind == 2:
        for _ in range(rng.integers(1, 4)):
            pos = int(rng.integers(0, len(arr)))
            if rng.random() < 0.5:
                arr[pos:pos] = rng.integers(0, 256, rng.integers(1, 20), dtype=np.uint8).tobytes()
            else:
                del arr[pos:pos + int(rng.integers(1, 20))]
    else:
        a, b = sorted(rng.integers(0, len(arr), 2))
        arr = arr[:a] + arr[b:]
    return bytes(arr)


def _undetected_bound(cases: int) -> float:
    # The SICK CRC's generator shares the factor (x + 1) with its (x + x^8) byte pairing, so
    # it checks 15 bits: a frame with two or more far-apart byte errors slips through with
    # probability 2^-15 (single-byte errors are always caught: see test below).
    return 3 + 4 * cases * 2.0 ** -15


def test_crc_catches_every_single_byte_error():
    from cgamap.drivers.lms2xx import _crc_tables

    lo, hi = _crc_tables()
    for n in (7, 210, 732, 816):   # telegram lengths without CRC
        i = np.arange(n - 1)
        delta = lo[n - 1 - i][:, 1:] ^ hi[n - 2 - i][:, 1:]   # error v at byte i
        assert (delta != 0).all()
        assert (lo[0, 1:] != 0).all()                        # error in the last byte


@settings(max_examples=max(1, FUZZ_EXAMPLES // 20), deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(st.integers(0, 2 ** 32 - 1), st.integers(1, 64))
def test_fuzz_lms_parser(seed, chunk):
    """20 cases per example (CGAMAP_FUZZ_EXAMPLES in all): random streams, mutated valid
    streams and cut streams only ever yield valid scans or counted errors; nothing raises."""
    rng = np.random.default_rng(seed)
    undetected = 0
    for _ in range(20):
        stream = _mutant(rng)
        scans, errors = _pipeline(stream, chunk)
        for s in scans:
            assert len(s.ranges) == 101 and s.ranges.dtype == np.float64
            undetected += np.nan_to_num(s.ranges, nan=-1.0).tobytes() not in _KEYS
        if stream == _CLEAN:
            assert len(scans) == 4
    assert undetected <= 1


@pytest.mark.slow
def test_fuzz_lms_parser_long():
    """``make fuzz``: a long run of byte-error mutations without hypothesis overhead."""
    rng = np.random.default_rng(11)
    clean = np.frombuffer(_CLEAN, np.uint8)
    undetected = 0
    for _ in range(FUZZ_EXAMPLES):
        arr = clean.copy()
        hit = rng.random(len(arr)) < rng.choice([1e-3, 1e-2, 0.1])
        arr[hit] = rng.integers(0, 256, int(hit.sum()))
        scans, _ = _pipeline(arr.tobytes(), int(rng.integers(1, 200)))
        for s in scans:
            undetected += np.nan_to_num(s.ranges, nan=-1.0).tobytes() not in _KEYS
    assert undetected <= _undetected_bound(FUZZ_EXAMPLES)


# -- the real driver against the twin on a pty ------------------------------------------------
@pytest.fixture
def twin(tmp_path):
    tw = Lms2xxTwin("corridor", link=str(tmp_path / "ttyLMS"), seed=1, time_scale=2.0,
                    noise=NoiseModel(sigma=0.01, dropout=0.0))
    tw.start()
    yield tw
    tw.stop()


def _driver(twin, **kw) -> Lms2xxDriver:
    kw.setdefault("session_baud", 500000)
    return Lms2xxDriver(twin.path, 0.5, **kw)


def test_init_stream_and_stop(twin):
    drv = _driver(twin)
    drv.open()
    try:
        assert drv.status_info.type_string == "LMS291-S05"
        assert (drv.status_info.angle, drv.status_info.resolution) == (180, 0.5)  # power-on
        assert twin.baud == 500000 and twin.streaming and (twin.angle, twin.res) == (180, 100)
        scans = list(drv.scans(20, timeout=2.0))
        assert len(scans) == 20
        assert [s.seq for s in scans] == list(range(20))
        s = scans[-1]
        assert len(s.ranges) == 181 and s.angle_min == pytest.approx(-np.pi / 2)
        assert s.range_max == pytest.approx(81.91)
        # the corridor is 2 m wide: left + right beams sum to about 2 m unless at a niche
        assert np.nanmin(s.ranges) > 0.2 and np.nanmax(s.ranges) < 25
        assert all(b.stamp_ns >= a.stamp_ns for a, b in zip(scans, scans[1:], strict=False))
        assert drv.errors.checksum == 0 and drv.errors.disconnects == 0
        drv.stop_streaming()
        assert not twin.streaming
        drv.transport.reset_input()
        assert drv.transport.read(4096, 0.2) == b""   # nothing streams any more
        single = drv.request_scan()
        assert len(single.ranges) == 181
    finally:
        drv.close()


def test_mm_units_and_interlaced_quarter_degree(twin):
    drv = _driver(twin, angle=100, resolution=0.25, units="mm")
    with drv:
        assert twin.config[6] == 1 and (twin.angle, twin.res) == (100, 25)
        scans = list(drv.scans(3, timeout=3.0))
    assert len(scans) == 3
    s = scans[-1]
    assert len(s.ranges) == 401 and s.range_max == pytest.approx(8.191)
    assert s.angle_increment == pytest.approx(np.radians(0.25))
    # interleaving is right if neighbouring beams agree (a wrong order would zig-zag)
    d = np.abs(np.diff(s.ranges))
    assert np.nanmedian(d) < 0.03


def test_half_degree_interlaced_and_realtime_index(tmp_path):
    with Lms2xxTwin("room", link=str(tmp_path / "tty"), interlace_half=True,
                    time_scale=2.0) as tw:
        with _driver(tw, resolution=0.5, realtime_indices=True) as drv:
            assert tw.config[4] & 0x02   # availability: send real-time indices
            scans = list(drv.scans(4, timeout=3.0))
        assert tw.baud == 9600 and not tw.streaming   # close() restores the power-on rate
    assert [len(s.ranges) for s in scans] == [361] * 4
    stamps = [s.device_stamp for s in scans]
    assert all(isinstance(v, int) for v in stamps)
    assert all((b - a) % 256 == 2 for a, b in zip(stamps, stamps[1:], strict=False))


def test_baud_detection_from_each_rate(twin):
    for start in (19200, 38400):
        twin.baud = start
        drv = _driver(twin, session_baud=9600)
        drv.open()
        assert drv.device_baud == 9600 and twin.baud == 9600
        assert drv.read_scan(5.0) is not None   # 9600 baud: ~1.3 scans/s at 2x time
        drv.close()


def test_reset_and_status(twin):
    with _driver(twin) as drv:
        drv.reset(timeout=5.0)
        assert drv.streaming and twin.baud == 500000
        assert drv.read_scan(2.0) is not None


def test_refusals_raise_device_errors(twin):
    with _driver(twin) as drv:
        with pytest.raises(DeviceError, match="variant"):
            drv.set_variant(100, 0.25)       # refused while streaming
        with pytest.raises(DeviceError, match="0x92"):
            drv.transact(b"\x55")           # unknown command
        drv.stop_streaming()
        reply = drv.transact(b"\x77" + bytes(34))   # not in installation mode: F7 00
        assert reply[:2] == b"\xF7\x00"
    with pytest.raises(ValueError):
        Lms2xxDriver(twin.path, angle=180, resolution=0.25)


def test_nak_byte_for_a_bad_crc(twin):
    with _driver(twin) as drv:
        drv.stop_streaming()
        good_send = drv.send
        drv.send = lambda p: drv.transport.write(frame(p)[:-1] + b"\x00")   # spoil the CRC
        with pytest.raises(DeviceError, match="NAK"):
            drv.transact(b"\x31", timeout=0.5, retries=1)
        assert drv.errors.device == 2 and twin.stats["bad_crc"] == 2
        drv.send = good_send
        assert drv.transact(b"\x31")[0] == 0xB1


def test_no_device_answers(tmp_path):
    from cgamap.drivers.sim.pty_device import PtyDevice

    with PtyDevice(str(tmp_path / "silent")) as dead:  # a port with nothing behind it
        drv = Lms2xxDriver(dead.path, probe_timeout=0.05)
        with pytest.raises(DeviceError, match="does not answer"):
            drv.open()
        assert drv.transport is None


def test_truncated_frames_are_dropped_and_stream_continues(twin):
    with _driver(twin) as drv:
        assert drv.read_scan(2.0) is not None
        twin.truncate(3)
        got = list(drv.scans(10, timeout=2.0))
    assert len(got) == 10
    assert twin.stats["truncated"] == 3
    assert drv.errors.checksum + drv.errors.framing >= 3


def test_stall_is_detected_and_streaming_resumes(twin):
    with _driver(twin, stall_timeout=0.4) as drv:
        assert drv.read_scan(2.0) is not None
        twin.stall(1.0)
        # scans already on the wire still arrive first
        read_until(drv, lambda: drv.errors.timeout > 0, 5.0, 0.5)
        assert drv.errors.timeout >= 1
        assert drv.read_scan(5.0) is not None


def test_byte_errors_1e3_deliver_intact_and_only_intact(tmp_path):
    """Twin injects byte errors at 1e-3: >= 99 % of intact scans arrive, no corrupted one."""
    tw = Lms2xxTwin("loop", link=str(tmp_path / "tty"), seed=3, time_scale=3.0,
                    noise=NoiseModel(sigma=0.01, dropout=0.01))
    tw.start()
    try:
        drv = _driver(tw)
        drv.open()  # the init sees errors too; transact retries cover them
        tw.fault_rate = 1e-3
        first = len(tw.sent)
        delivered = []
        for scan in drv.scans(900, timeout=3.0):
            counts = np.where(np.isnan(scan.ranges), 8191, np.rint(scan.ranges / 0.01))
            delivered.append(counts.astype("<u2").tobytes())
        drv.close()
    finally:
        tw.stop()
    sent = list(tw.sent)[first:]
    index = {v: i for i, (v, _) in enumerate(sent)}
    positions = [index.get(d) for d in delivered]
    assert None not in positions[1:]                  # every delivered scan was sent ...
    positions = [p for p in positions if p is not None]
    assert all(sent[p][1] for p in positions)          # ... and sent intact
    lo, hi = positions[0], positions[-1]
    intact = [i for i in range(lo, hi + 1) if sent[i][1]]
    corrupted = sum(1 for i in range(lo, hi + 1) if not sent[i][1])
    assert corrupted > 50                               # the faults really happened
    ratio = len(set(positions)) / len(intact)
    print(f"intact sent {len(intact)}, delivered {len(set(positions))} ({ratio:.4f}), "
          f"corrupted {corrupted}, errors {drv.errors}")
    assert ratio >= 0.99


def test_unplug_replug_streams_again_within_2s(twin):
    drv = _driver(twin, stall_timeout=0.5)
    drv.open()
    try:
        assert drv.read_scan(2.0) is not None
        twin.unplug()
        read_until(drv, lambda: drv.errors.disconnects > 0, 3.0, 0.2)
        assert drv.errors.disconnects >= 1 and not drv.connected   # loss reported
        assert drv.read_scan(0.5) is None                           # nothing to read
        twin.replug()
        t_back = time.monotonic()
        scan = drv.read_scan(5.0)
        dt = time.monotonic() - t_back
        assert scan is not None and drv.connected
        print(f"streaming again {dt:.3f} s after the device returned")
        assert dt < 2.0
        assert twin.baud == 500000   # the power-cycled device was found at 9600 and switched
    finally:
        drv.close()
