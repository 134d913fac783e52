"""Fuzzing the SCIP parser: random and mutated byte streams in arbitrary chunks.

Only well-formed replies and scans may come out (a scan re-encodes to bytes that parse back to
itself), every loss is counted, nothing raises, nothing hangs.  A single corrupted byte never
yields a wrong scan.  Examples: ``CGAMAP_FUZZ_EXAMPLES`` (default 10000); ``make fuzz`` runs
the slow variant with many more.  Each hypothesis example draws a seed (and raw bytes) and
runs ``BATCH`` streams from it, so FUZZ_EXAMPLES counts streams, not hypothesis examples.
"""

from __future__ import annotations

import os
import signal
from contextlib import contextmanager

import numpy as np
import pytest
from cgamap.drivers.scip import TIMESTAMP_PERIOD, ScipParser, ScipReply, ScipScan
from cgamap.drivers.sim.hokuyo import scan_reply
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

FUZZ_EXAMPLES = int(os.environ.get("CGAMAP_FUZZ_EXAMPLES", "10000"))
BATCH = 10   # streams per hypothesis example: hypothesis' own overhead dominates otherwise
WIDTH = {"D": 3, "S": 2, "E": 6}


@contextmanager
def no_hang(seconds: int):
    """Fail (instead of hanging the suite) if the body runs for more than ``seconds``."""
    def _alarm(*_a):
        raise TimeoutError(f"parser fuzz did not finish within {seconds} s")
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def check_item(item) -> None:
    """A parser output must be a well-formed reply or scan."""
    assert isinstance(item, ScipReply | ScipScan), type(item)
    if isinstance(item, ScipReply):
        assert isinstance(item.echo, str) and isinstance(item.status, str)
        assert item.status != "99"                      # 99 always means a scan
        assert all(isinstance(x, str) for x in item.lines)
        return
    enc = item.command[1]
    n = -(-(item.end - item.start + 1) // item.cluster)
    assert item.command[0] in "GM" and enc in WIDTH and 0 <= item.start <= item.end
    assert item.ranges_mm.shape == (n,) and item.ranges_mm.dtype == np.uint32
    assert 0 <= item.timestamp < TIMESTAMP_PERIOD <= item.device_ms + TIMESTAMP_PERIOD
    assert (item.remaining is None) == (item.command[0] == "G")
    assert (item.intensity is not None) == (enc == "E")
    # it re-encodes to bytes that parse back to exactly itself
    status = "99" if item.command[0] == "M" else "00"
    again = ScipParser().feed(scan_reply(item.echo, status, item.timestamp, item.ranges_mm, enc,
                                         item.intensity))
    assert len(again) == 1 and again[0].ranges_mm.tolist() == item.ranges_mm.tolist()


def feed_chunks(parser: ScipParser, data: bytes, cuts: list[int]) -> list:
    out = []
    pos = 0
    for c in sorted(set(min(max(0, x), len(data)) for x in cuts)) + [len(data)]:
        out += parser.feed(data[pos:c])
        pos = c
    return out


def valid_stream(rng: np.random.Generator, k: int) -> tuple[bytes, list[tuple[int, list]]]:
    """``k`` random valid replies (scans of every kind, acks, info) and the scans in them."""
    parts, scans = [], []
    for i in range(k):
        kind = int(rng.integers(0, 5))
        if kind == 3:
            parts.append(b"QT\n00P\n\n")
            continue
        if kind == 4:
            parts.append(b"MD0000001001000\n00P\n\nPP\n00P\nDMIN:23;7\nAMAX:1080;Z\n\n")
            continue
        enc = "DSE"[kind]
        start = int(rng.integers(0, 40))
        end = start + int(rng.integers(0, 80))
        cl = int(rng.integers(1, 4))
        n = -(-(end - start + 1) // cl)
        vals = rng.integers(0, 4096 if enc == "S" else 1 << 18, n).astype(np.uint32)
        inten = rng.integers(0, 1 << 18, n).astype(np.uint32) if enc == "E" else None
        ts = int(rng.integers(0, TIMESTAMP_PERIOD))
        if rng.random() < 0.5:
            echo, status = f"M{enc}{start:04d}{end:04d}{cl:02d}0{i % 100:02d}", "99"
        else:
            echo, status = f"G{enc}{start:04d}{end:04d}{cl:02d}", "00"
        parts.append(scan_reply(echo, status, ts, vals, enc, inten))
        scans.append((ts, vals.tolist()))
    return b"".join(parts), scans


# -- random streams ---------------------------------------------------------------------

TOKENS = [b"\n", b"\n\n", b"MD0000001001000\n", b"GD0000000201\n", b"99b\n", b"00P\n",
          b"QT\n", b"0000P\n", b"E\n", b";", b"0", b"o", b"\xff"]


@settings(max_examples=max(1, FUZZ_EXAMPLES // BATCH), deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=200), st.integers(0, 2**32 - 1))
def test_fuzz_random_streams(raw, seed):
    """Raw random bytes spliced into a soup of SCIP-looking tokens and random runs."""
    rng = np.random.default_rng(seed)
    for _ in range(BATCH):
        n = int(rng.integers(0, 31))
        pieces = [TOKENS[int(rng.integers(0, len(TOKENS)))] if rng.random() < 0.6
                  else rng.bytes(int(rng.integers(0, 40))) for _ in range(n)]
        pieces.insert(int(rng.integers(0, n + 1)), raw)
        cuts = rng.integers(0, 2000, int(rng.integers(0, 7))).tolist()
        p = ScipParser()
        with no_hang(20):
            out = feed_chunks(p, b"".join(pieces), cuts)
        for item in out:
            check_item(item)
        assert p.scans + p.replies == len(out)
        assert all(v >= 0 for v in p.errors.as_dict().values())


# -- mutated valid streams -----------------------------------------------------------------

def mutate(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for op, pos, size, junk in ops:
        if not b:
            break
        i = pos % len(b)
        if op == "flip":
            b[i] ^= junk[0] or 1
        elif op == "set":
            b[i] = junk[0]
        elif op == "delete":
            del b[i:i + size]
        elif op == "insert":
            b[i:i] = junk
        elif op == "dup":
            b[i:i] = b[i:i + size]
        else:
            del b[i:]
    return bytes(b)


OPS = ["flip", "set", "delete", "insert", "dup", "cut"]


def random_ops(rng: np.random.Generator, n: int) -> list:
    return [(OPS[int(rng.integers(0, len(OPS)))], int(rng.integers(0, 1 << 20)),
             int(rng.integers(1, 300)), rng.bytes(int(rng.integers(1, 8)))) for _ in range(n)]


@settings(max_examples=max(1, FUZZ_EXAMPLES // BATCH), deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
def test_fuzz_mutated_streams(seed):
    rng = np.random.default_rng(seed)
    for _ in range(BATCH):
        data, scans = valid_stream(rng, int(rng.integers(1, 5)))
        ops = random_ops(rng, int(rng.integers(0, 5)))
        cuts = rng.integers(0, len(data) + 1, int(rng.integers(0, 5))).tolist()
        p = ScipParser()
        with no_hang(20):
            out = feed_chunks(p, mutate(data, ops), cuts)
        for item in out:
            check_item(item)
        if not ops:                     # untouched: everything arrives, nothing counted
            assert [(s.timestamp, s.ranges_mm.tolist()) for s in out
                    if isinstance(s, ScipScan)] == scans
            assert sum(p.errors.as_dict().values()) == 0


@settings(max_examples=max(1, FUZZ_EXAMPLES // BATCH), deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1))
def test_fuzz_one_bad_byte_never_yields_a_wrong_scan(seed):
    rng = np.random.default_rng(seed)
    for _ in range(BATCH):
        data, scans = valid_stream(rng, 3)
        i = int(rng.integers(0, len(data)))
        bad = data[:i] + bytes([data[i] ^ int(rng.integers(1, 256))]) + data[i + 1:]
        out = [s for s in ScipParser().feed(bad) if isinstance(s, ScipScan)]
        original = {(ts, tuple(v)) for ts, v in scans}
        for s in out:
            assert (s.timestamp, tuple(s.ranges_mm.tolist())) in original
        assert len(out) >= len(scans) - 1               # at most the hit scan is lost


@pytest.mark.slow
def test_fuzz_long_run():
    """``make fuzz``: many more mutated streams, without hypothesis' bookkeeping."""
    rng = np.random.default_rng(2024)
    p = ScipParser()                    # one parser across all runs: state must never stick
    with no_hang(3600):
        for _ in range(FUZZ_EXAMPLES):
            data, _scans = valid_stream(rng, int(rng.integers(1, 5)))
            ops = random_ops(rng, int(rng.integers(0, 4)))
            cuts = rng.integers(0, len(data) + 1, int(rng.integers(0, 5))).tolist()
            for item in feed_chunks(p, mutate(data, ops), cuts):
                check_item(item)
        # and it still reads a clean scan afterwards
        out = p.feed(b"\n\n" + scan_reply("GD0000000901", "00", 7, np.arange(10), "D"))
        assert [s.ranges_mm.tolist() for s in out if isinstance(s, ScipScan)][-1] == \
            list(range(10))
