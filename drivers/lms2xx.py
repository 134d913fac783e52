"""SICK LMS2xx (LMS200/211/221/291) over RS-232/RS-422: telegrams, CRC, scans, the driver.

Wire format (reference lasers.md §1): ``02 ADR LEN_LO LEN_HI payload CRC_LO CRC_HI`` with LEN
the payload length (command/reply byte + data + status in replies), ADR 0x00 host→LMS and 0x80
LMS→host, and SICK's own CRC-16 (§1.2; not a library preset).  After every telegram it receives
the LMS sends one raw byte, 0x06 ACK or 0x15 NAK, then a framed reply whose first payload byte
is the command + 0x80 (0x92 is the NAK telegram).

The receive side resynchronises on ``02 80``: frames with a bad CRC are dropped and counted
(``errors.checksum``), skipped bytes are counted (``errors.framing``), and sliding goes on one
byte at a time so a good frame behind a damaged one is never lost.

Scans: continuous mode ``20 24`` streams ``B0`` telegrams.  Values are masked per measuring
mode (config byte [6]); units come from bits 14-15 of the count word (cm, mm, dm).  Values at
the top of the range (within 8 of the mask, e.g. 8183-8191 for 13 bits) and dazzled beams
(mode 00, bit 15) mean no return and become NaN.  When the variant's resolution is finer than
1° the LMS may send interlaced partial scans (count word bits 11-12 give the offset index
0.25° · k); the :class:`ScanAssembler` interleaves a complete set into one full scan and
drops (and counts) incomplete sets.

Stamps: a scan's ``stamp_ns`` is the best host-time estimate of the instant its (last) sweep
ended, which is when the LMS starts sending it: the arrival of the telegram's first byte (STX),
never later than the last byte's arrival minus the wire time of the bytes after the first
(10 bits a byte at the session baud, on a real serial line: a pty moves bytes at no rate at
all).  With real-time indices on, ``device_stamp`` is the sweep counter unwrapped (one count a
sweep at 75 Hz; the wire byte is its low 8 bits) and the stamp goes through a
:class:`~.device_clock.DeviceClock` on that count, so a scan the host read late keeps the
instant it was measured.  The clock and the counter start afresh on every (re)connect.
"""

from __future__ import annotations

import logging
import math
import os
import stat
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from .device_clock import DeviceClock, WrappingCounter
from .laser import DeviceError, LaserDriver
from .messages import ErrorCounters, LaserScan
from .transport import Transport, parse_device_url

log = logging.getLogger(__name__)

STX = 0x02
ACK = 0x06
NAK = 0x15
HOST_ADDR = 0x80
MAX_PAYLOAD = 812
BAUD_PROBE_ORDER = (9600, 19200, 38400, 500000)
BAUD_CODES = {38400: 0x40, 19200: 0x41, 9600: 0x42, 500000: 0x48}
PASSWORD = b"SICK_LMS"
SWEEP_HZ = 75.0  # native mirror rate (one 1° sweep)
# Fixed for every supported variant (0.5°/0.25°: 2/4 sweeps): sicktoolbox_wrapper sicklms.cpp
SWEEP_NS = round(1e9 / SWEEP_HZ)  # host ns per count of the real-time index
# The sweep rate is held by the mirror's motor control, not by a quartz clock, so counts
# times SWEEP_NS drift against the host clock by the motor's rate error; the DeviceClock's
# least offset is taken over a short window (2 s) so that a rate error e costs at most
# 2 s * e (2 ms at 1e-3), while at 38400 baud (5-10 telegrams/s) the window still holds
# several telegrams, one of which came straight through.
CLOCK_WINDOW_SWEEPS = int(2.0 * SWEEP_HZ)

# measuring mode -> (range mask, dazzle bit or 0, reflector bits mask and shift)
_MODE_MASKS = {
    0x00: (0x1FFF, 0x8000, 0, 0), 0x01: (0x1FFF, 0, 0xE000, 13), 0x02: (0x1FFF, 0, 0, 0),
    0x03: (0x3FFF, 0, 0xC000, 14), 0x04: (0x3FFF, 0, 0, 0),
    0x05: (0x7FFF, 0, 0x8000, 15), 0x06: (0x7FFF, 0, 0, 0),
    0x0F: (0xFFFF, 0, 0, 0), 0x3F: (0xFFFF, 0, 0, 0),
}
_UNIT_M = {0: 0.01, 1: 0.001, 2: 0.1}  # count word bits 14-15 -> metres per count
UNIT_CODES = {"cm": 0, "mm": 1, "dm": 2}


class FrameError(ValueError):
    """A telegram that passed the CRC but is inconsistent (wrong length for its content)."""


# -- CRC ----------------------------------------------------------------------------------
_CRC_TABLES: tuple[np.ndarray, np.ndarray] | None = None


def _crc_tables() -> tuple[np.ndarray, np.ndarray]:
    """T_lo[k, b] = x^k · b and T_hi[k, b] = x^k · (b << 8) in GF(2)[x] mod the SICK polynomial.

    The SICK CRC step is crc = x·crc ⊕ w_i with w_i = (previous byte << 8) | byte, so the CRC of
    N bytes is ⊕_i x^(N-1-i) · w_i: linear, hence two table look-ups per byte and one XOR
    reduction, with no Python loop over the bytes.
    """
    global _CRC_TABLES
    if _CRC_TABLES is None:
        n = 4 + MAX_PAYLOAD + 1
        lo = np.empty((n, 256), np.uint16)
        hi = np.empty((n, 256), np.uint16)
        b = np.arange(256, dtype=np.uint32)
        cur_lo, cur_hi = b.copy(), b << 8
        for k in range(n):
            lo[k], hi[k] = cur_lo, cur_hi
            for cur in (cur_lo, cur_hi):
                top = (cur & 0x8000) != 0
                cur[:] = ((cur << 1) & 0xFFFF) ^ np.where(top, 0x8005, 0)
        _CRC_TABLES = (lo, hi)
    return _CRC_TABLES


def crc16_sick(data: bytes) -> int:
    """SICK LMS2xx CRC-16 of ``data`` (STX through the status byte), reference §1.2."""
    a = np.frombuffer(bytes(data), dtype=np.uint8)
    n = len(a)
    if n == 0:
        return 0
    lo, hi = _crc_tables()
    if n > len(lo):
        raise ValueError(f"telegram too long for the CRC tables: {n} bytes")
    k = np.arange(n - 1, -1, -1)
    acc = np.bitwise_xor.reduce(lo[k, a])
    if n > 1:
        acc ^= np.bitwise_xor.reduce(hi[k[1:], a[:-1]])
    return int(acc)


def frame(payload: bytes, address: int = 0x00) -> bytes:
    """Frame a payload: STX, address, LEN (LE), payload, CRC (LE)."""
    if not 0 < len(payload) <= MAX_PAYLOAD:
        raise ValueError(f"payload length {len(payload)} outside 1..{MAX_PAYLOAD}")
    head = bytes([STX, address, len(payload) & 0xFF, len(payload) >> 8]) + bytes(payload)
    return head + crc16_sick(head).to_bytes(2, "little")


# -- receive side ---------------------------------------------------------------------------
@dataclass
class Event:
    """What the parser found: kind "ack", "nak" or "frame" (payload set).

    ``stamp_ns``: arrival (host monotonic ns) of the chunk that completed it; ``first_ns``:
    of the chunk that held its first byte (None: same as ``stamp_ns``); ``size``: its bytes
    on the wire (STX through CRC).
    """

    kind: str
    payload: bytes = b""
    stamp_ns: int = 0
    first_ns: int | None = None
    size: int = 0


def wire_ns(nbytes: int, baud: int) -> int:
    """Nanoseconds ``nbytes`` take on an 8N1 serial line (10 bits a byte)."""
    return nbytes * 10_000_000_000 // baud


def telegram_start_ns(ev: Event, baud: int | None = None) -> int:
    """Best host-time estimate of when ``ev``'s first byte arrived: the arrival of the chunk
    that held it, and with ``baud`` (a real line's rate) never later than the last byte's
    arrival minus the wire time of the bytes after the first."""
    first = ev.stamp_ns if ev.first_ns is None else ev.first_ns
    if baud and ev.size > 1:
        first = min(first, ev.stamp_ns - wire_ns(ev.size - 1, baud))
    return first


class FrameParser:
    """Incremental LMS→host telegram parser with resync on ``02 80`` (see module docstring)."""

    def __init__(self, errors: ErrorCounters | None = None, address: int = HOST_ADDR) -> None:
        self.errors = errors if errors is not None else ErrorCounters()
        self.buf = bytearray()
        self._sync = bytes([STX, address])
        # chunks with bytes still in buf: (stream offset just past the chunk, its stamp);
        # buf[0] is at stream offset _base
        self._chunks: deque[tuple[int, int]] = deque()
        self._base = 0

    def reset(self) -> None:
        self.buf.clear()
        self._chunks.clear()
        self._base = 0

    def feed(self, data: bytes, stamp_ns: int | None = None) -> list[Event]:
        """Add bytes that arrived at ``stamp_ns`` (default: now); return the events completed
        by them, in order."""
        buf = self.buf
        buf += data
        stamp = time.monotonic_ns() if stamp_ns is None else stamp_ns
        if data:
            self._chunks.append((self._base + len(buf), stamp))
        out: list[Event] = []
        while buf:
            i = buf.find(self._sync)
            if i < 0:
                keep = 1 if buf[-1] == STX else 0
                self._skip(len(buf) - keep, out, stamp)
                break
            if i:
                self._skip(i, out, stamp)
            if len(buf) < 4:
                break
            n = buf[2] | (buf[3] << 8)
            if n == 0 or n > MAX_PAYLOAD:
                self._skip(1, out, stamp)
                continue
            if len(buf) < 6 + n:
                break
            crc = buf[4 + n] | (buf[5 + n] << 8)
            if crc != crc16_sick(bytes(buf[:4 + n])):
                self.errors.checksum += 1
                self._skip(1, out, stamp, count=False)
                continue
            out.append(Event("frame", bytes(buf[4:4 + n]), stamp, self._chunks[0][1], 6 + n))
            self._drop(6 + n)
        return out

    def _drop(self, n: int) -> None:
        """Delete n leading bytes of buf and the chunks no byte of buf is from any more."""
        del self.buf[:n]
        self._base += n
        while self._chunks and self._chunks[0][0] <= self._base:
            self._chunks.popleft()

    def _skip(self, n: int, out: list[Event], stamp: int, count: bool = True) -> None:
        """Drop n leading bytes; lone ACK/NAK bytes become events, others count as framing."""
        chunk = self.buf[:n]
        acks = chunk.count(ACK) + chunk.count(NAK)
        if acks:
            for b in chunk:
                if b == ACK or b == NAK:
                    out.append(Event("ack" if b == ACK else "nak", b"", stamp))
        if count:
            self.errors.framing += n - acks
        self._drop(n)


# -- scans ----------------------------------------------------------------------------------
@dataclass
class B0Scan:
    """One decoded ``B0`` telegram (possibly a partial scan of an interlaced set)."""

    ranges: np.ndarray            # metres, NaN = no return
    partial: int                  # partial-scan index (offset partial · 0.25°)
    unit: float                   # metres per count
    range_max: float              # metres at the top of the range mask
    status: int
    rt_index: int | None = None   # the real-time index byte as sent
    reflect: np.ndarray | None = None
    stamp_ns: int = 0             # when its (last) sweep ended, host monotonic ns
    sweep: int | None = None      # rt_index unwrapped (the driver's sweep count)


def decode_b0(payload: bytes, measuring_mode: int = 0, stamp_ns: int = 0) -> B0Scan:
    """Decode a ``B0`` payload (``B0 W v0..v(n-1) [rt] status``); reference §1.6."""
    if len(payload) < 4 or payload[0] != 0xB0:
        raise FrameError("not a B0 scan telegram")
    w = payload[1] | (payload[2] << 8)
    n = w & 0x3FF
    extra = len(payload) - (3 + 2 * n)  # status, or real-time index + status
    if n == 0 or extra not in (1, 2):
        raise FrameError(f"B0 count {n} does not fit a payload of {len(payload)} bytes")
    unit_code = (w >> 14) & 0x3
    if unit_code not in _UNIT_M:
        raise FrameError("B0 count word has reserved unit bits 11")
    unit = _UNIT_M[unit_code]
    mask, dazzle, refl_mask, refl_shift = _MODE_MASKS.get(measuring_mode, _MODE_MASKS[0])
    raw = np.frombuffer(payload, dtype="<u2", count=n, offset=3)
    counts = raw & mask
    ranges = counts * unit
    bad = counts >= mask - 8
    if dazzle:
        bad |= (raw & dazzle) != 0
    ranges = np.where(bad, np.nan, ranges)
    reflect = ((raw & refl_mask) >> refl_shift).astype(np.uint8) if refl_mask else None
    return B0Scan(ranges=ranges, partial=(w >> 11) & 0x3, unit=unit, range_max=mask * unit,
                  status=payload[-1], rt_index=payload[-2] if extra == 2 else None,
                  reflect=reflect, stamp_ns=stamp_ns)


def variant_count(angle: int, resolution: float) -> int:
    """Number of values of a full scan: 181 for 180°/1°, 361 for 180°/0.5°, 401 for 100°/0.25°."""
    return int(round(angle / resolution)) + 1


@dataclass
class ScanAssembler:
    """Turns B0 telegrams into full :class:`LaserScan` objects for one variant.

    A telegram with the full count is a scan.  With ``k = 1° / resolution`` > 1, telegrams with
    partial index 0..k-1 and the counts of ``full[p::k]`` are interleaved into one scan when the
    whole set arrived in order; a set broken by a lost telegram is dropped and counted.
    """

    angle: int = 180
    resolution: float = 1.0
    errors: ErrorCounters = field(default_factory=ErrorCounters)
    _parts: list[B0Scan] = field(default_factory=list)

    @property
    def full_count(self) -> int:
        return variant_count(self.angle, self.resolution)

    @property
    def interlace(self) -> int:
        return max(1, int(round(1.0 / self.resolution)))

    def add(self, part: B0Scan) -> LaserScan | None:
        n_full, k = self.full_count, self.interlace
        n = len(part.ranges)
        if n == n_full:
            if self._parts:
                self._abandon()
            return self._scan(part.ranges, part, sweeps=k)
        p = part.partial
        if k == 1 or p >= k or n != len(range(p, n_full, k)):
            self.errors.framing += 1  # a scan of another variant: ignore it
            return None
        if p != len(self._parts):
            if self._parts:
                self._abandon()
            if p != 0:
                return None
        self._parts.append(part)
        if len(self._parts) < k:
            return None
        full = np.empty(n_full)
        for i, q in enumerate(self._parts):
            full[i::k] = q.ranges
        parts, self._parts = self._parts, []
        return self._scan(full, parts[-1], sweeps=k)

    def _abandon(self) -> None:
        self.errors.dropped += 1
        self._parts = []

    def _scan(self, ranges: np.ndarray, last: B0Scan, sweeps: int) -> LaserScan:
        return LaserScan(
            seq=0, stamp_ns=last.stamp_ns,
            angle_min=-math.radians(self.angle / 2.0),
            angle_increment=math.radians(self.resolution),
            ranges=ranges, range_min=0.0, range_max=last.range_max,
            scan_time=sweeps / SWEEP_HZ,
            device_stamp=last.rt_index if last.sweep is None else last.sweep,
            intensities=None, frame="laser")


# -- driver -----------------------------------------------------------------------------------
@dataclass
class Lms2xxStatus:
    """Fields of the ``B1`` status reply and the type string."""

    type_string: str
    operating_mode: int
    measuring_mode: int
    angle: int
    resolution: float
    raw: bytes


class Lms2xxDriver(LaserDriver):
    """Driver for a SICK LMS2xx on a serial line (see the module docstring).

    ``session_baud`` is the rate used while streaming (default: the URL's ``baudrate``/``baud``,
    else 38400; 500000 needs RS-422).  ``angle``/``resolution`` select the variant,
    ``units`` ("cm"/"mm"), ``measuring_mode`` and ``realtime_indices`` (availability flag
    0x02: a one-byte sweep counter in each B0, unwrapped into ``device_stamp`` and the
    stamps' :class:`~.device_clock.DeviceClock`) the config block; None keeps the device's
    setting (with real-time indices on, the counter is used either way).  ``restore_baud``
    returns the LMS to 9600 on close.
    ``wire_time``: bound scan stamps by the wire time at the session baud (see the module
    docstring); None = only on a serial port that is not a pseudo-terminal.
    A reconnect inside :meth:`read_scan` (baud probing, init) may take up to about 2 s
    beyond the call's timeout.
    """

    model = "lms2xx"
    default_baud = 9600

    def __init__(self, device: str | Transport, timeout: float = 0.5, *,
                 session_baud: int | None = None, angle: int = 180, resolution: float = 1.0,
                 units: str | None = "cm", measuring_mode: int | None = None,
                 realtime_indices: bool | None = None, restore_baud: bool = True,
                 baud_switch_delay: float = 0.05, probe_timeout: float = 0.25,
                 wire_time: bool | None = None, **kw) -> None:
        super().__init__(device, timeout, **kw)
        if session_baud is None:
            session_baud = parse_device_url(self.url).baud or 38400
        if session_baud not in BAUD_CODES:
            raise ValueError(f"LMS2xx baud must be one of {sorted(BAUD_CODES)}")
        if (angle, resolution) not in ((180, 1.0), (180, 0.5), (100, 1.0), (100, 0.5),
                                       (100, 0.25)):
            raise ValueError(f"LMS2xx has no variant {angle}°/{resolution}°")
        if units is not None and units not in ("cm", "mm"):
            raise ValueError("units must be 'cm' or 'mm'")
        self.session_baud = session_baud
        self.angle, self.resolution = angle, resolution
        self.units, self.measuring_mode_wanted = units, measuring_mode
        self.realtime_indices = realtime_indices
        self.restore_baud = restore_baud
        self.baud_switch_delay = baud_switch_delay
        self.probe_timeout = probe_timeout
        self.parser = FrameParser(self.errors)
        self.assembler = ScanAssembler(angle, resolution, self.errors)
        self.measuring_mode = 0
        self.device_baud: int | None = None
        self.status_info: Lms2xxStatus | None = None
        self._pending: list[Event] = []
        self.streaming = False
        self.wire_time = wire_time
        self._wire_real = False                  # wire_time resolved for the open transport
        self.sweeps = WrappingCounter(8, SWEEP_NS)
        self.clock = DeviceClock(unit_ns=SWEEP_NS, window=CLOCK_WINDOW_SWEEPS)
        # the last scan's last telegram: arrival of its last byte (what stamp_ns used to be)
        self.arrival_ns: int | None = None

    # -- low level ---------------------------------------------------------------------------
    def _events(self, timeout: float) -> list[Event]:
        """Events already parsed, else those from the next bytes (b"" after timeout)."""
        if self._pending:
            ev, self._pending = self._pending, []
            return ev
        data = self.transport.read(4096, timeout)
        return self.parser.feed(data) if data else []

    def send(self, payload: bytes) -> None:
        self.transport.write(frame(payload))

    def transact(self, payload: bytes, timeout: float = 1.0, retries: int = 2,
                 expect: int | None = None) -> bytes:
        """Send a telegram, await its ACK and the reply ``command + 0x80``; the reply payload.

        Other frames (e.g. streamed scans) are skipped.  NAK byte or 0x92 → DeviceError;
        no reply → one retry, then TransportError-free DeviceError("timeout").
        """
        want = (payload[0] + 0x80) & 0xFF if expect is None else expect
        for attempt in range(retries + 1):
            self.send(payload)
            deadline = time.monotonic() + timeout
            nak = False
            while (left := deadline - time.monotonic()) > 0:
                for ev in self._events(left):
                    if ev.kind == "nak":
                        nak = True
                    elif ev.kind == "frame":
                        if ev.payload[0] == want:
                            return ev.payload
                        if ev.payload[0] == 0x92:
                            raise DeviceError(f"LMS refused {payload[:2].hex(' ')} (0x92)")
                if nak:
                    break
            if nak:
                self.errors.device += 1
                if attempt == retries:
                    raise DeviceError(f"LMS NAKed telegram {payload[:2].hex(' ')}")
                continue
            self.errors.timeout += 1
        raise DeviceError(f"no reply 0x{want:02X} to {payload[:2].hex(' ')}")

    def _mode(self, mode: int, extra: bytes = b"", timeout: float = 1.0) -> None:
        reply = self.transact(bytes([0x20, mode]) + extra, timeout)
        if len(reply) < 2 or reply[1] != 0x00:
            raise DeviceError(f"LMS refused operating mode 0x{mode:02X}")

    # -- init ---------------------------------------------------------------------------------
    def detect_baud(self) -> int:
        """Find the LMS's current rate: the session rate first (it survives a cable unplug),
        then 9600 → 19200 → 38400 → 500000, probing with the error/test request ``32``."""
        order = [self.session_baud] + [b for b in BAUD_PROBE_ORDER if b != self.session_baud]
        timeouts = self.errors.timeout  # unanswered probes are expected, not errors
        for baud in order:
            self.transport.set_baud(baud)
            self._flush()
            try:
                self.transact(b"\x32", self.probe_timeout, retries=0)
            except DeviceError:
                continue
            finally:
                self.errors.timeout = timeouts
            self.device_baud = baud
            return baud
        raise DeviceError("LMS2xx does not answer at 9600, 19200, 38400 or 500000 baud")

    def set_baud(self, baud: int) -> None:
        """Switch the LMS and the host to ``baud`` for this session (until power-off)."""
        self._mode(BAUD_CODES[baud])
        self.transport.set_baud(baud)
        time.sleep(self.baud_switch_delay)
        self._flush()
        self.device_baud = baud

    def _flush(self) -> None:
        self.transport.reset_input()
        self.parser.reset()
        self._pending = []

    def read_status(self) -> Lms2xxStatus:
        """Type string (``3A``) and status (``31``): operating/measuring mode, variant."""
        t = self.transact(b"\x3A")
        s = self.transact(b"\x31")
        if len(s) < 112:
            raise DeviceError(f"B1 status reply too short ({len(s)} bytes)")
        res = int.from_bytes(s[109:111], "little") / 100.0
        self.status_info = Lms2xxStatus(
            type_string=t[1:-1].decode("ascii", "replace").strip("\x00 "),
            operating_mode=s[8], measuring_mode=s[102],
            angle=int.from_bytes(s[107:109], "little"), resolution=res, raw=s)
        return self.status_info

    def read_config(self) -> bytes:
        """The 32/34 configuration bytes (``74`` → ``F4``), indexed like the ``77`` payload
        minus its command byte (so config[5] is byte [6], the measuring mode)."""
        r = self.transact(b"\x74")
        if len(r) not in (34, 36):
            raise DeviceError(f"F4 config reply of unexpected length {len(r)}")
        return r[1:-1]

    def write_config(self, config: bytes) -> None:
        """Installation mode, then ``77`` + config bytes; back to request mode."""
        self._mode(0x00, PASSWORD, timeout=3.0)
        r = self.transact(b"\x77" + bytes(config), timeout=15.0)
        if len(r) < 2 or r[1] != 0x01:
            raise DeviceError("LMS refused the configuration block")
        self._mode(0x25)

    def set_variant(self, angle: int, resolution: float) -> None:
        """``3B`` angle res (only in request mode)."""
        res = int(round(resolution * 100))
        r = self.transact(b"\x3B" + angle.to_bytes(2, "little") + res.to_bytes(2, "little"))
        if len(r) < 2 or r[1] != 0x01:
            raise DeviceError(f"LMS refused variant {angle}°/{resolution}°")

    def start_streaming(self) -> None:
        self._mode(0x24, timeout=3.0)
        self.streaming = True

    def stop_streaming(self) -> None:
        self._mode(0x25, timeout=3.0)
        self.streaming = False

    def request_scan(self, timeout: float = 2.0) -> LaserScan | None:
        """One scan on request (``30 01``), outside continuous mode."""
        r = self.transact(b"\x30\x01", timeout)
        return self._scan_from(Event("frame", r, time.monotonic_ns(), size=len(r) + 6))

    def reset(self, timeout: float = 60.0) -> None:
        """Reset (``10``): await ``91`` and the ``90`` power-on telegram, then re-initialise."""
        self.transact(b"\x10", expect=0x91)
        self.transport.set_baud(9600)  # the LMS comes back up at its power-on rate
        self.parser.reset()
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            if any(ev.kind == "frame" and ev.payload[0] == 0x90 for ev in self._events(left)):
                break
        else:
            raise DeviceError("no power-on telegram 0x90 after reset")
        self._start()

    def _start(self) -> None:
        self._flush()
        self.streaming = False
        self.clock.reset()       # a reconnected LMS may have been power-cycled: new counter
        self.sweeps.reset()
        self._wire_real = self.wire_time if self.wire_time is not None \
            else not _is_pty(self.transport)
        self.detect_baud()
        if self.device_baud != self.session_baud:
            self.set_baud(self.session_baud)
        self._mode(0x25)  # request mode: variant and config changes need it
        st = self.read_status()
        config = bytearray(self.read_config())
        changed = False
        if self.units is not None and config[6] != UNIT_CODES[self.units]:
            config[6] = UNIT_CODES[self.units]
            changed = True
        if self.measuring_mode_wanted is not None and config[5] != self.measuring_mode_wanted:
            config[5] = self.measuring_mode_wanted
            changed = True
        if self.realtime_indices is not None and \
                bool(config[4] & 0x02) != self.realtime_indices:
            config[4] ^= 0x02
            changed = True
        if changed:
            self.write_config(config)
        self.measuring_mode = config[5]
        if (st.angle, st.resolution) != (self.angle, self.resolution):
            self.set_variant(self.angle, self.resolution)
        self.assembler = ScanAssembler(self.angle, self.resolution, self.errors)
        self.start_streaming()

    def _stop(self) -> None:
        if self.streaming:
            self.stop_streaming()
        if self.restore_baud and self.device_baud not in (None, 9600):
            self.set_baud(9600)  # as sicktoolbox does: leave the LMS at its power-on rate

    # -- scans --------------------------------------------------------------------------------
    def _scan_from(self, ev: Event) -> LaserScan | None:
        p = ev.payload
        if p[0] != 0xB0:
            return None
        baud = self.transport.baud if self._wire_real and self.transport is not None else None
        start = telegram_start_ns(ev, baud)
        try:
            part = decode_b0(p, self.measuring_mode, start)
        except FrameError as exc:
            self.errors.framing += 1
            log.debug("%s: %s", self.url, exc)
            return None
        if part.status & 0x07:
            self.errors.device += 1
        if part.rt_index is not None:
            part.sweep = self.sweeps.unwrap(part.rt_index, start)
            part.stamp_ns = self.clock.stamp(part.sweep, start)
        scan = self.assembler.add(part)
        if scan is not None:
            self.arrival_ns = ev.stamp_ns
        return scan

    def _receive_scan(self, timeout: float) -> LaserScan | None:
        deadline = time.monotonic() + timeout
        while True:
            events = self._events(max(0.0, deadline - time.monotonic()))
            for i, ev in enumerate(events):
                if ev.kind != "frame":
                    continue
                scan = self._scan_from(ev)
                if scan is not None:
                    self._pending = events[i + 1:] + self._pending
                    return scan
            if time.monotonic() >= deadline:
                return None


def _is_pty(transport: Transport | None) -> bool:
    """Whether ``transport`` is a serial port on a pseudo-terminal (Unix98 pty slaves have
    major numbers 136-143 on Linux), where bytes take no wire time."""
    tr = getattr(transport, "inner", transport)  # through a SpyTransport
    path = getattr(tr, "path", None)
    if not path:
        return False
    try:
        st = os.stat(path)
    except OSError:
        return False
    return stat.S_ISCHR(st.st_mode) and 136 <= os.major(st.st_rdev) <= 143


__all__ = [
    "Lms2xxDriver", "Lms2xxStatus", "FrameParser", "FrameError", "ScanAssembler", "B0Scan",
    "Event", "crc16_sick", "frame", "decode_b0", "variant_count", "telegram_start_ns", "wire_ns",
]
