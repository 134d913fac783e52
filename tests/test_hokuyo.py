"""Hokuyo SCIP 2.0: byte-level vectors, the parser, and the real driver over a real pyserial
port on the twin's pty (init, streaming, single scans, stop, every fault)."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from cgamap.drivers.hokuyo import HokuyoDriver, ScipError, scan_to_message
from cgamap.drivers.scip import (
    TIMESTAMP_PERIOD,
    ScipParser,
    ScipReply,
    ScipScan,
    SensorInfo,
    TimestampUnwrapper,
    checksum,
    decode,
    decode_array,
    line_ok,
    parse_fields,
    status_text,
)
from cgamap.drivers.sim.hokuyo import HokuyoTwin, encode_values, scan_reply
from cgamap.drivers.sim.world import NoiseModel
from cgamap.drivers.transport import open_transport

# -- byte-level vectors (reference lasers.md section 3.1) -------------------------------------

UTM_PP = ["MODL:UTM-30LX-EW;I", "DMIN:23;7", "DMAX:60000;J", "ARES:1440;^", "AMIN:0;?",
          "AMAX:1080;Z", "AFRT:540;0", "SCAN:2400;U"]


@pytest.mark.parametrize("chars,value", [("CB", 1234), ("1Dh", 5432), ("m2@0", 16000000)])
def test_decode_vectors(chars, value):
    assert decode(chars) == value
    assert decode_array(chars.encode() * 3, len(chars)).tolist() == [value] * 3
    assert encode_values(np.array([value]), len(chars)) == chars.encode()


@pytest.mark.parametrize("body,char", [(b"00", "P"), (b"99", "b"), (b"0E", "e"),
                                       (b"Hokuyo", "o")])
def test_checksum_vectors(body, char):
    assert chr(checksum(body)) == char
    assert line_ok(body + char.encode())
    assert not line_ok(body + b"Q")


def test_info_lines_checksum_excludes_semicolon():
    p = ScipParser()
    block = ("PP\n00P\n" + "\n".join(UTM_PP) + "\n\n").encode()
    (reply,) = p.feed(block)
    assert isinstance(reply, ScipReply) and reply.status == "00"
    f = parse_fields(reply.lines)
    assert f["MODL"] == "UTM-30LX-EW" and f["DMAX"] == "60000" and f["SCAN"] == "2400"
    bad = block.replace(b"DMIN:23;7", b"DMIN:24;7")
    assert p.feed(bad) == [] and p.errors.checksum == 1 and p.errors.dropped == 1


def test_sensor_info_angles_and_limits():
    utm = SensorInfo.from_fields(parse_fields([x[:-2] for x in UTM_PP]))
    assert (utm.dmin, utm.dmax, utm.ares, utm.amin, utm.amax, utm.afrt) == \
        (23, 60000, 1440, 0, 1080, 540)
    assert utm.angle_of(0) == pytest.approx(-math.radians(135))
    assert utm.angle_of(1080) == pytest.approx(math.radians(135))
    assert utm.scan_time == pytest.approx(0.025)
    urg = SensorInfo.from_fields(dict(DMIN="20", DMAX="5600", ARES="1024", AMIN="44",
                                      AMAX="725", AFRT="384", SCAN="600"))
    assert math.degrees(urg.angle_of(44)) == pytest.approx(-119.53, abs=0.01)
    assert math.degrees(urg.angle_of(725)) == pytest.approx(119.88, abs=0.01)
    with pytest.raises(ValueError, match="DMAX"):
        SensorInfo.from_fields(dict(DMIN="20"))


def test_resync_vector_yields_two_qt_replies():
    # seqsense/urg_stamped test_scip2.cpp
    p = ScipParser()
    out = p.feed(b"QT\n00P\n\nFOO\nBAR\nQT\n\nQT\n\nQT\n00P\n\n")
    assert [(r.echo, r.status) for r in out] == [("QT", "00"), ("QT", "00")]


def _utm_block(ts=1000, values=None, echo="MD0000108001000", status="99"):
    values = np.arange(1081, dtype=np.uint32) * 7 + 23 if values is None else values
    return scan_reply(echo, status, ts, values, echo[1]), values


def test_scan_reply_size_and_decode_in_any_chunking():
    block, values = _utm_block()
    assert len(block) == 3372          # reference: UTM-30LX MD scan block
    for step in (1, 7, 65, 4096):
        p = ScipParser()
        out = []
        for i in range(0, len(block), step):
            out += p.feed(block[i:i + step], stamp_ns=i)
        (scan,) = out
        assert isinstance(scan, ScipScan)
        assert scan.ranges_mm.tolist() == values.tolist()
        assert (scan.start, scan.end, scan.cluster, scan.remaining) == (0, 1080, 1, 0)
        assert scan.timestamp == 1000
        assert scan.stamp_ns == (len(block) - 1) // step * step   # chunk with the last LF
        assert p.errors.as_dict() == dict.fromkeys(p.errors.as_dict(), 0)


def test_every_single_byte_error_in_a_scan_is_caught():
    """Flip each byte of a scan reply (to a value that keeps the 6-bit checksum when possible):
    the scan is dropped and counted, or comes out unchanged; the next scan always arrives."""
    block, values = _utm_block()
    nxt, _ = _utm_block(ts=1025)
    rng = np.random.default_rng(1)
    for pos in range(len(block)):
        b = block[pos]
        new = (b + 64) & 0xFF if rng.random() < 0.5 else b ^ int(rng.integers(1, 256))
        corrupted = block[:pos] + bytes([new]) + block[pos + 1:]
        p = ScipParser()
        out = p.feed(corrupted + nxt)
        scans = [s for s in out if isinstance(s, ScipScan)]
        assert all(s.ranges_mm.tolist() == values.tolist() for s in scans)
        assert scans and scans[-1].timestamp == 1025, pos
        if len(scans) == 1:     # the corrupted one was dropped, and counted
            assert p.errors.dropped + p.errors.checksum + p.errors.framing > 0, pos
            assert not [r for r in out if isinstance(r, ScipReply)]


def test_truncated_reply_then_next_scan():
    block, values = _utm_block()
    nxt, _ = _utm_block(ts=2000)
    for cut in (20, 100, 1700, len(block) - 2):
        p = ScipParser()
        out = p.feed(block[:cut] + nxt)
        assert [s.timestamp for s in out if isinstance(s, ScipScan)] == [2000]
        assert p.errors.dropped >= 1


def test_intensity_and_two_char_encodings():
    mm = np.array([100, 200, 4095, 23], dtype=np.uint32)
    inten = np.array([1, 2, 3, 4000], dtype=np.uint32)
    p = ScipParser()
    (me,) = p.feed(scan_reply("ME0000000301000", "99", 5, mm, "E", inten))
    assert me.ranges_mm.tolist() == mm.tolist() and me.intensity.tolist() == inten.tolist()
    (gs,) = p.feed(scan_reply("GS0000000301", "00", 6, mm, "S"))
    assert gs.command == "GS" and gs.remaining is None and gs.ranges_mm.tolist() == mm.tolist()
    # cluster 2 over steps 0..4: 3 values
    (cl,) = p.feed(scan_reply("GD0000000402", "00", 7, mm[:3], "D"))
    assert cl.cluster == 2 and len(cl.ranges_mm) == 3


def test_scan_to_message_no_return_is_nan():
    utm = SensorInfo.from_fields(parse_fields([x[:-2] for x in UTM_PP]))
    scan = ScipScan("MD", "MD0000000402000", 0, 4, 2, 0, 5, 5,
                    np.array([1, 1000, 60001], dtype=np.uint32), None, 42)
    msg = scan_to_message(scan, utm)
    assert np.isnan(msg.ranges[0]) and msg.ranges[1] == 1.0 and np.isnan(msg.ranges[2])
    assert msg.angle_min == pytest.approx(utm.angle_of(0.5))
    assert msg.angle_increment == pytest.approx(2 * utm.step_angle)
    assert msg.stamp_ns == 42 and msg.device_stamp == 5 and msg.range_max == 60.0


def test_timestamp_unwrapping():
    u = TimestampUnwrapper()
    raw = [TIMESTAMP_PERIOD - 50, TIMESTAMP_PERIOD - 25, 0, 25, 50]
    assert [u(r) for r in raw] == [TIMESTAMP_PERIOD - 50, TIMESTAMP_PERIOD - 25,
                                   TIMESTAMP_PERIOD, TIMESTAMP_PERIOD + 25,
                                   TIMESTAMP_PERIOD + 50]
    assert u(40) == TIMESTAMP_PERIOD + 40        # small step back: not a wrap


def test_status_codes_are_explained():
    assert "abnormal" in status_text("0L") and "unstable" in status_text("0M")
    assert "hardware" in status_text("55")
    assert "0L" in str(ScipError("BM", "0L")) and "abnormal" in str(ScipError("BM", "0L"))


# -- the real driver over a real pyserial port on the twin's pty ----------------------------

@pytest.fixture
def twin(tmp_path):
    tw = HokuyoTwin(link=str(tmp_path / "ttyACM0"), seed=3, speed=4.0,
                    noise=NoiseModel(sigma=0.005, dropout=0.02))
    tw.start()
    yield tw
    tw.close()


def assert_same_mm(ranges: np.ndarray, sent_mm: np.ndarray, dmin=23, dmax=60000) -> None:
    """Delivered metres equal the twin's millimetres; its error codes came out NaN."""
    no_return = (sent_mm < dmin) | (sent_mm > dmax)
    np.testing.assert_array_equal(np.isnan(ranges), no_return)
    np.testing.assert_array_equal(np.round(ranges[~no_return] * 1000), sent_mm[~no_return])


def _driver(tw, **kw) -> HokuyoDriver:
    kw.setdefault("command_timeout", 1.0)
    kw.setdefault("stall_timeout", 0.5)
    return HokuyoDriver(tw.url, 0.5, **kw)


def test_init_and_continuous_streaming(twin):
    with _driver(twin) as d:
        assert d.info.model == "UTM-30LX" and d.info.steps == 1081
        assert twin.commands[:6] == ["QT", "VV", "PP", "II", "BM", "MD0000108001000"]
        scans = list(d.scans(10, timeout=2.0))
    assert len(scans) == 10
    assert [s.seq for s in scans] == list(range(10))
    stamps = np.array([s.device_stamp for s in scans])
    assert np.all(np.diff(stamps) > 0) and np.all(np.diff(stamps) % 25 == 0)   # 40 Hz turns
    for s in scans:
        assert len(s.ranges) == 1081
        assert s.angle_min == pytest.approx(-math.radians(135))
        assert s.angle_increment == pytest.approx(math.radians(0.25))
        ok = np.isfinite(s.ranges)
        assert 0.9 < ok.mean() < 1.0          # 2% dropouts come out NaN
        assert np.all(s.ranges[ok] < 25.0)    # the corridor is 20 m long
        assert sum(s.errors.values()) == 0
    # the ranges match the world: the twin's ray cast for the same device time
    rec = {x.timestamp: x for x in twin.sent}
    for s in scans:
        assert_same_mm(s.ranges, rec[s.device_stamp].values)
    # ground truth: the world seen from the trajectory at the scan's device time
    for s in scans[:3]:
        truth = twin.world.scan(s.device_stamp / 1000.0, s.angles, 60.0, None, None)
        ok = np.isfinite(s.ranges) & np.isfinite(truth)
        assert np.median(np.abs(s.ranges[ok] - truth[ok])) < 0.01      # noise sigma 5 mm
    assert twin.commands[-1] == "QT" and not twin.streaming


def test_single_scan_mode_and_options(twin):
    with _driver(twin, mode="single", encoding="E", start=180, end=900, cluster=3) as d:
        assert not twin.streaming
        s = d.read_scan(2.0)
        assert twin.commands[-1] == "GE0180090003"
        assert len(s.ranges) == 241 and s.intensities is not None
        assert s.angle_min == pytest.approx(d.info.angle_of(181))
    with _driver(twin, encoding="S", skip=1) as d:
        s = d.read_scan(2.0)
        assert twin.commands[-1] == "MS0000108001100" and len(s.ranges) == 1081
        # 2-char values saturate at 4095 mm: farther returns are no return
        assert np.nanmax(s.ranges) <= 4.095


def test_stop_and_resume(twin):
    with _driver(twin) as d:
        assert d.read_scan(2.0) is not None
        d.stop()
        assert not twin.streaming
        n = len(twin.sent)
        time.sleep(0.1)
        assert len(twin.sent) == n               # nothing streams after QT
        d.resume()
        assert d.read_scan(2.0) is not None


def test_urg04lx_and_reply_size(tmp_path):
    with HokuyoTwin("URG-04LX", link=str(tmp_path / "tty"), speed=4.0) as tw:
        with open_transport(tw.path, 1.0) as t:
            t.write(b"BM\n")
            assert t.read_until(b"\n\n") == b"BM\n00P\n\n"
            t.write(b"GD0044072500\n")
            raw = t.read_until(b"\n\n", timeout=2.0)
            assert len(raw) == 2134             # reference: URG-04LX GD reply size
        with _driver(tw) as d:
            s = d.read_scan(2.0)
            assert len(s.ranges) == 682 and d.info.afrt == 384
            assert np.nanmax(s.ranges) <= 5.6


def test_scip11_switch_tm_mode_and_time_sync(tmp_path):
    with HokuyoTwin(link=str(tmp_path / "tty"), scip1=True, speed=1.0) as tw:
        with _driver(tw) as d:
            assert tw.commands[:2] == ["QT", "SCIP2.0"]
            offset = d.sync_time(samples=3)
            assert tw.commands[-8:] == ["QT", "TM0", "TM1", "TM1", "TM1", "TM2", "BM",
                                        "MD0000108001000"]
            s = d.read_scan(2.0)
            host = d.device_to_host_ns(s.device_stamp)
            assert host == s.device_stamp * 1_000_000 + offset
            # the device stamps a scan shortly before the host has its last byte (the
            # estimate is good to about the device's 1 ms resolution)
            assert s.stamp_ns - 50_000_000 < host < s.stamp_ns + 2_000_000
        tw._tm_mode = True                      # left in time-adjust mode by someone
        with _driver(tw) as d:
            assert tw.commands[-8:-5] == ["QT", "TM2", "QT"]
            assert d.read_scan(2.0) is not None


def test_rs232_baud_detection_and_switch(tmp_path):
    # an RS-232 URG-04LX at its power-on 19200 baud; the URL says 115200 (wrong)
    with HokuyoTwin("URG-04LX", link=str(tmp_path / "tty"), baud=19200, speed=4.0) as tw:
        d = HokuyoDriver(f"serial://{tw.path}?baud=115200", 0.5, command_timeout=0.3,
                         baud=500000)
        with d:
            assert d.read_scan(2.0) is not None
            assert "SS500000" in tw.commands and tw.baud == 500000
            assert tw.dev.host_baud() == 500000
        with pytest.raises(ValueError, match="baud"):
            HokuyoDriver(tw.path, baud=12345)


def test_ethernet_model_over_tcp_with_unplug():
    with HokuyoTwin("UST-10LX", tcp_port=0, speed=4.0) as tw:
        assert tw.url.startswith("tcp://127.0.0.1:")
        with _driver(tw) as d:
            assert d.info.model == "UST-10LX" and d.info.dmax == 30000
            assert len(d.read_scan(2.0).ranges) == 1081
            tw.disconnect()                     # port closed: connection refused
            for _ in range(10):
                if d.read_scan(0.3) is None:
                    break
            assert d.errors.disconnects >= 1 and not d.connected
            tw.reconnect()
            assert d.read_scan(2.0) is not None


def test_timestamp_wrap_through_driver(tmp_path):
    with HokuyoTwin(link=str(tmp_path / "tty"), speed=4.0,
                    clock0_ms=TIMESTAMP_PERIOD - 400) as tw, _driver(tw) as d:
        stamps = [s.device_stamp for s in d.scans(20, timeout=2.0)]
    assert np.all(np.diff(stamps) > 0) and stamps[-1] > TIMESTAMP_PERIOD


def test_device_error_status_is_clear(tmp_path):
    with HokuyoTwin(link=str(tmp_path / "tty"), status="01") as tw:
        d = _driver(tw, reconnect=False)
        with pytest.raises(ScipError, match="'BM' answered '01'"):
            d.open()
        d.close()


def test_fault_truncated_replies(twin):
    with _driver(twin) as d:
        assert d.read_scan(2.0) is not None
        twin.truncate(3)
        got = list(d.scans(12, timeout=2.0))
        assert len(got) == 12 and d.errors.dropped >= 3
        rec = {x.timestamp: x for x in twin.sent}
        assert all(rec[s.device_stamp].intact for s in got)


def test_unstable_blocks_and_reset(twin):
    with _driver(twin) as d:
        assert d.read_scan(2.0) is not None
        twin.unstable(2)
        got = list(d.scans(5, timeout=2.0))
        assert len(got) == 5 and d.errors.device == 2        # 0M blocks counted, skipped
        d.reset()
        assert twin.commands[-3:] == ["RS", "BM", "MD0000108001000"]
        assert d.read_scan(2.0) is not None


def test_reply_garbage_is_bounded():
    p = ScipParser()
    p.feed(b"VV\n00P\n" + b"AB" + bytes([checksum(b"AB")]) + b"\n" * 1)
    for _ in range(200):
        p.feed(b"AB" + bytes([checksum(b"AB")]) + b"\n")
    assert p.feed(b"\n") == [] and p.errors.framing > 0   # never a 200-line reply
    assert p.feed(b"QT\n00P\n\n")[0].echo == "QT"


def test_fault_stall_then_streaming_again(twin):
    with _driver(twin) as d:
        assert d.read_scan(2.0) is not None
        twin.stall(1.0)
        got = [d.read_scan(0.3) for _ in range(4)]          # ~1.2 s of stall
        assert None in got
        assert d.read_scan(3.0) is not None                 # after the stall
        assert d.errors.timeout >= 1


def test_fault_unplug_and_replug_within_2s(twin):
    with _driver(twin) as d:
        assert d.read_scan(2.0) is not None
        twin.disconnect()
        for _ in range(10):                 # scans already received may still come out
            if d.read_scan(0.5) is None:
                break
        assert d.errors.disconnects + d.errors.timeout >= 1
        assert not d.connected
        twin.reconnect()
        scan = d.read_scan(2.0)                             # the required bound
        assert scan is not None and d.connected
        assert twin.commands[-6:] == ["QT", "VV", "PP", "II", "BM", "MD0000108001000"]


@pytest.mark.parametrize("model,n_scans,speed", [
    ("UTM-30LX", 3000, 20.0),
    pytest.param("URG-04LX", 6000, 60.0, marks=pytest.mark.slow),   # ~700 intact scans
])
def test_byte_errors_1e3_intact_scans_arrive_corrupted_never(tmp_path, model, n_scans, speed):
    """Twin at byte error rate 1e-3: >= 99% of the scans sent intact must be delivered, and
    none that was corrupted (unless no SCIP receiver could tell, which is counted)."""
    with HokuyoTwin(model, link=str(tmp_path / "tty"), speed=speed, seed=11,
                    fault_rate=1e-3) as tw:
        with _driver(tw, stall_timeout=2.0, command_timeout=0.3) as d:   # init under errors
            delivered = {}
            deadline_scans = n_scans
            while len(tw.sent) < deadline_scans:
                s = d.read_scan(3.0)
                assert s is not None, d.errors
                delivered[s.device_stamp % TIMESTAMP_PERIOD] = s
            tw.fault_rate = 0.0
            for _ in range(3):          # the last ones in flight
                s = d.read_scan(1.0)
                if s is not None:
                    delivered[s.device_stamp % TIMESTAMP_PERIOD] = s
        sent = list(tw.sent)[: deadline_scans]
    intact = [x for x in sent if x.intact]
    arrived = sum(x.timestamp in delivered for x in intact)
    rec = {x.timestamp: x for x in tw.sent}
    corrupt_delivered = [ts for ts in delivered if not rec[ts].intact]
    undetectable = [ts for ts in corrupt_delivered if rec[ts].undetectable]
    print(f"sent {len(sent)}, intact {len(intact)}, arrived {arrived}, "
          f"corrupted delivered {len(corrupt_delivered)} (undetectable {len(undetectable)}), "
          f"errors {d.errors}")
    assert len(intact) >= 50
    assert arrived >= 0.99 * len(intact)
    assert corrupt_delivered == undetectable
    dmin, dmax = (20, 5600) if model == "URG-04LX" else (23, 60000)
    for ts, s in delivered.items():             # every delivered scan is what was sent
        if rec[ts].intact:
            assert_same_mm(s.ranges, rec[ts].values, dmin, dmax)


def test_process_epoch_is_this_process_start(monkeypatch):
    from cgamap.drivers.sim.hokuyo import process_epoch

    monkeypatch.delenv("CGAMAP_SIM_EPOCH_NS", raising=False)
    assert 0.0 < time.monotonic() - process_epoch() < 3600.0 or \
        process_epoch() == pytest.approx(time.monotonic(), abs=1.0)   # non-Linux fallback
    monkeypatch.setenv("CGAMAP_SIM_EPOCH_NS", "5000000000")
    assert process_epoch() == 5.0


# -- the CLI twin ----------------------------------------------------------------------------

def test_sim_device_cli_serves_until_sigterm():
    # the sim-device subcommand alone (other subcommands' modules may be mid-change)
    boot = ("import argparse, sys; from cgamap.daemon import cmd_sim; "
            "p = argparse.ArgumentParser(); cmd_sim.register(p.add_subparsers()); "
            "a = p.parse_args(sys.argv[1:]); sys.exit(a.func(a))")
    cmd = [sys.executable, "-c", boot, "sim-device", "hokuyo", "--seed", "2"]
    # the device clock starts at the epoch its starter gives (here: 10 s ago)
    env = dict(os.environ, CGAMAP_SIM_EPOCH_NS=str(time.monotonic_ns() - 10_000_000_000))
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    try:
        path = proc.stdout.readline().strip()
        assert path and os.path.exists(path)
        with HokuyoDriver(path, 0.5, command_timeout=1.0) as d:
            s = d.read_scan(2.0)
            assert s is not None and s.device_stamp >= 10_000
        proc.send_signal(signal.SIGUSR1)        # unplug for 1 s, then back at the same path
        d2 = HokuyoDriver(path, 0.5, command_timeout=1.0)
        assert d2.read_scan(4.0) is not None    # connects (again) once the twin is back
        d2.close()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
        assert not os.path.exists(path)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)


def test_non_ascii_command_is_answered_and_twin_keeps_serving(tmp_path):
    """QA: a Dynamixel packet (bytes >= 0x80) sent to the twin killed its serving thread."""
    with HokuyoTwin("URG-04LX", link=str(tmp_path / "tty"), speed=4.0) as tw:
        with open_transport(tw.path, 1.0) as t:
            t.write(b"\xff\xff\xfd\x00\x01\x03\x00\x01\x19\x4e\n")
            assert t.read_until(b"\n\n", timeout=1.0) == b"???\x00\x01\x03\x00\x01\x19N\n0Ee\n\n"
            t.write(b"BM\n")
            assert t.read_until(b"\n\n", timeout=1.0) == b"BM\n00P\n\n"
        with _driver(tw) as d:
            assert len(d.read_scan(2.0).ranges) == 682
        assert tw._thread.is_alive()


def test_a_command_that_raises_is_counted_not_fatal(tmp_path, monkeypatch):
    with HokuyoTwin("URG-04LX", link=str(tmp_path / "tty"), speed=4.0) as tw:
        real = tw._command

        def flaky(line: str) -> None:
            if line == "XX":
                raise RuntimeError("boom")
            real(line)
        monkeypatch.setattr(tw, "_command", flaky)
        with open_transport(tw.path, 1.0) as t:
            t.write(b"XX\nBM\n")
            assert t.read_until(b"\n\n", timeout=1.0) == b"BM\n00P\n\n"
        assert tw.command_errors == 1
