"""Hokuyo SCIP 2.0, the pure part: checksums, character decoding, the sensor description,
status codes and an incremental stream parser (bytes in, replies and scans out).

Nothing here does I/O, so the parser can be fed any byte stream (fuzzing, replay, the twin's
own output) and only ever returns valid replies and scans; everything else it drops and counts
in :attr:`ScipParser.errors`.  Protocol facts: ``shared/reference/lasers.md`` section 3.

A reply is a block of lines ended by an empty line::

    echo (the command as sent)      e.g. ``MD0000108001000``
    status: 2 chars + checksum      ``99b`` (scan follows, continuous) / ``00P`` (ok)
    [timestamp: 4 chars + checksum] data replies only
    [data lines: <= 64 chars + checksum each; values may straddle lines]
    (empty line)

Every line after the echo carries a checksum, ``chr((sum(bytes) & 0x3F) + 0x30)``; info lines
(``KEY:value;C``) exclude the ``;`` from it.  The parser enforces all of them: one bad line
drops the whole reply.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from .messages import ErrorCounters

TIMESTAMP_PERIOD = 1 << 24          # the SCIP timestamp is a 24-bit millisecond counter
MAX_DATA_PER_LINE = 64              # data characters per line before the checksum
MAX_LINE = 1024                     # longer lines are garbage (longest real ones: ~70)
MAX_REPLY_LINES = 64                # info replies have ~10 lines; more is garbage
CHARS_PER_VALUE = {"D": 3, "S": 2, "E": 6}   # E: 3-char range + 3-char intensity

# Echo lines of the data commands; search() tolerates garbage before the echo (a corrupted
# tail of the previous reply merges into the next echo when its final LF is hit).
_M_ECHO = re.compile(rb"(M[DSE])(\d{4})(\d{4})(\d{2})(\d)(\d{2})(;[ -~]{0,16})?$")
_G_ECHO = re.compile(rb"(G[DSE])(\d{4})(\d{4})(\d{2})(;[ -~]{0,16})?$")
_OTHER_ECHO = re.compile(
    rb"(QT|BM|RS|RT|RB|VV|PP|II|TM[012]|SS\d{6}|CR\d{2}|HS[01]|SCIP2\.0|%SL)(;[ -~]{0,16})?$")

# Status codes (reference section 3.2; hokuyolx ``reply_statuses``; parameter and hardware
# codes from the SCIP 2.0 specification, not confirmed against a device).
STATUS_TEXT = {
    "00": "ok",
    "99": "scan data follows",
    "01": "starting step not a number (or: laser cannot be switched on, malfunction)",
    "02": "end step not a number (or: laser already on)",
    "03": "cluster count not a number",
    "04": "end step out of range",
    "05": "end step smaller than starting step",
    "06": "scan interval not a number",
    "07": "number of scans not a number",
    "0D": "command too long",
    "0E": "command not defined (or: sensor is in time-adjust mode)",
    "0F": "command not supported by this model",
    "0G": "user string too long",
    "0H": "command too short",
    "0L": "sensor in abnormal state",
    "0M": "sensor unstable (laser or motor not ready)",
    "10": "denied",
    "98": "resumed after a hardware fault",
}


def status_text(status: str) -> str:
    """Human meaning of a 2-char status code (ranges 21-49 and 50-97 are hardware faults)."""
    if status in STATUS_TEXT:
        return STATUS_TEXT[status]
    if status.isdigit() and 21 <= int(status) <= 49:
        return "processing stopped to verify an error"
    if status.isdigit() and 50 <= int(status) <= 97:
        return "hardware trouble (laser, motor or internal)"
    return "unknown status"


def checksum(data: bytes) -> int:
    """SCIP checksum byte of ``data``: the low 6 bits of the byte sum, plus 0x30."""
    return (sum(data) & 0x3F) + 0x30


def line_ok(line: bytes) -> bool:
    """Whether a line (without LF) ends in the checksum of what precedes it."""
    return len(line) >= 2 and checksum(line[:-1]) == line[-1]


def decode(chars: bytes | str) -> int:
    """Decode SCIP characters (6 bits each, offset 0x30, most significant first).

    ``CB`` = 1234, ``1Dh`` = 5432, ``m2@0`` = 16000000 (reference vectors).
    """
    if isinstance(chars, str):
        chars = chars.encode("ascii")
    v = 0
    for c in chars:
        v = (v << 6) | ((c - 0x30) & 0x3F)
    return v


def decode_array(data: bytes, width: int) -> np.ndarray:
    """Decode a run of ``width``-character values at once (vectorised); len % width must be 0."""
    raw = (np.frombuffer(data, dtype=np.uint8) - 0x30).astype(np.uint32) & 0x3F
    raw = raw.reshape(-1, width)
    out = np.zeros(raw.shape[0], dtype=np.uint32)
    for k in range(width):  # width <= 4: a loop over character positions, not over values
        out = (out << 6) | raw[:, k]
    return out


class TimestampUnwrapper:
    """Turn the 24-bit SCIP millisecond counter into a monotonic count (it wraps every ~4.66 h).

    A step backwards by more than half the period is a wrap; smaller steps back (a reset
    device, reordering) are passed through unchanged.
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._offset = 0

    def __call__(self, raw: int) -> int:
        if self._last is not None and self._last - raw > TIMESTAMP_PERIOD // 2:
            self._offset += TIMESTAMP_PERIOD
        self._last = raw
        return raw + self._offset


@dataclass(frozen=True)
class SensorInfo:
    """What ``VV``/``PP``/``II`` say about the sensor.  Distances in mm, angles in steps."""

    model: str
    dmin: int          # DMIN: shortest valid range, mm
    dmax: int          # DMAX: longest valid range, mm
    ares: int          # ARES: steps per full turn
    amin: int          # AMIN: first measurable step
    amax: int          # AMAX: last measurable step
    afrt: int          # AFRT: step pointing forward (x axis)
    scan_rpm: int      # SCAN: mirror speed, rev/min
    vendor: str = ""
    product: str = ""
    firmware: str = ""
    protocol: str = ""
    serial: str = ""
    state: str = ""    # II STAT text
    extra: dict[str, str] = field(default_factory=dict)

    @property
    def step_angle(self) -> float:
        return 2.0 * math.pi / self.ares

    def angle_of(self, step: float) -> float:
        """Angle of a step, counter-clockwise from forward: (step − AFRT)·2π/ARES."""
        return (step - self.afrt) * self.step_angle

    @property
    def scan_time(self) -> float:
        return 60.0 / self.scan_rpm if self.scan_rpm else 0.0

    @property
    def steps(self) -> int:
        return self.amax - self.amin + 1

    @classmethod
    def from_fields(cls, fields: dict[str, str]) -> SensorInfo:
        """Build from merged ``KEY -> value`` of VV, PP and II; raises ValueError if PP is short."""
        def num(key: str) -> int:
            if key not in fields:
                raise ValueError(f"hokuyo: PP reply lacks {key}")
            m = re.match(r"\s*(-?\d+)", fields[key])
            if not m:
                raise ValueError(f"hokuyo: PP {key} is not a number: {fields[key]!r}")
            return int(m.group(1))

        known = {"MODL", "DMIN", "DMAX", "ARES", "AMIN", "AMAX", "AFRT", "SCAN",
                 "VEND", "PROD", "FIRM", "PROT", "SERI", "STAT"}
        info = cls(model=fields.get("MODL", ""), dmin=num("DMIN"), dmax=num("DMAX"),
                   ares=num("ARES"), amin=num("AMIN"), amax=num("AMAX"), afrt=num("AFRT"),
                   scan_rpm=num("SCAN"), vendor=fields.get("VEND", ""),
                   product=fields.get("PROD", ""), firmware=fields.get("FIRM", ""),
                   protocol=fields.get("PROT", ""), serial=fields.get("SERI", ""),
                   state=fields.get("STAT", ""),
                   extra={k: v for k, v in fields.items() if k not in known})
        if info.ares <= 0 or not 0 <= info.amin <= info.amax or info.dmax <= info.dmin:
            raise ValueError(f"hokuyo: implausible PP values {fields}")
        return info


def parse_fields(lines: list[str]) -> dict[str, str]:
    """``KEY:value`` lines (checksums already stripped) into a dict."""
    out: dict[str, str] = {}
    for line in lines:
        key, sep, value = line.partition(":")
        if sep:
            out[key.strip()] = value.strip()
    return out


@dataclass
class ScipReply:
    """A non-scan reply: echo, status and the payload lines (checksums verified and stripped)."""

    echo: str
    status: str
    lines: list[str]
    stamp_ns: int | None = None
    legacy: bool = False   # SCIP 1.1 style (one status char, no checksums)

    @property
    def command(self) -> str:
        return self.echo


@dataclass
class ScipScan:
    """One decoded scan reply of GD/GS/GE or MD/MS/ME."""

    command: str            # "MD", "GS", ...
    echo: str
    start: int              # first step
    end: int                # last step
    cluster: int            # steps merged per value (>= 1)
    remaining: int | None   # M*: scans still to come (0 for endless), None for G*
    timestamp: int          # raw 24-bit device milliseconds
    device_ms: int          # unwrapped device milliseconds
    ranges_mm: np.ndarray   # uint32, one per value
    intensity: np.ndarray | None
    stamp_ns: int | None = None


@dataclass
class _Block:
    echo: bytes
    status: bytes
    scan: bool
    cmd: str = ""
    start: int = 0
    end: int = 0
    cluster: int = 1
    remaining: int | None = None
    expected: int = 0                  # data characters expected (scan)
    timestamp: int | None = None
    data: list[bytes] = field(default_factory=list)
    size: int = 0
    bad: bool = False
    legacy: bool = False
    bodyless: bool = False             # an ack or error of a data command: no lines follow


def _data_echo(echo: bytes) -> tuple[re.Match[bytes] | None, bool]:
    m = _M_ECHO.search(echo)
    if m:
        return m, True
    return _G_ECHO.search(echo), False


def _echo_like(line: bytes, anywhere: bool) -> bool:
    """Whether ``line`` is an echo: fully (``anywhere=False``) or at its end after garbage."""
    for rx in (_M_ECHO, _G_ECHO, _OTHER_ECHO):
        m = rx.search(line)
        if m and (anywhere or m.start() == 0):
            return True
    return False


_ALPHABET = bytes(range(0x30, 0x70))
_STATUS_CHARS = b"0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ"


def _in_alphabet(data: bytes) -> bool:
    """Whether every byte is a SCIP data character (0x30..0x6F)."""
    return not data.translate(None, _ALPHABET)



def _is_status(line: bytes) -> bool:
    """Two status characters (digits, capitals) and their checksum."""
    return len(line) == 3 and line_ok(line) and not line[:2].translate(None, _STATUS_CHARS)


class ScipParser:
    """Incremental SCIP 2.0 reply parser.

    ``feed(data, stamp_ns)`` returns the replies and scans completed by ``data``;
    ``stamp_ns`` (the host time the bytes arrived) is copied into what they complete.
    Bad input never raises: it is dropped and counted in :attr:`errors`
    (``checksum``: lines failing theirs; ``framing``: misplaced, overlong or missing lines;
    ``dropped``: replies and scans thrown away because of those).

    A scan is delivered only if its echo names a data command, its status fits it (``99`` for
    M*, ``00`` for G*), its timestamp and every data line pass their checksums, all data
    characters lie in the 0x30..0x6F alphabet, and the data length is exactly what the echo's
    step range, cluster count and encoding call for.  Resynchronisation: a reply ends at the
    empty line; when that line is lost (a corrupted LF, a truncated reply), a valid status line
    right after an echo-like line starts the next reply, so one damaged reply costs at most
    itself.
    """

    def __init__(self) -> None:
        self.errors = ErrorCounters()
        self.unwrap = TimestampUnwrapper()
        self.scans = 0
        self.replies = 0
        self._buf = bytearray()
        self._skip_to_lf = False
        self._cand: bytes | None = None     # an echo waiting for its status line
        self._block: _Block | None = None
        self._prev: bytes | None = None     # previous line inside a block
        self._prev_rejected = False

    def reset(self) -> None:
        """Forget any partial reply (after reconnecting); counters and the unwrapper stay."""
        if self._block is not None or self._cand is not None or self._buf:
            self.errors.framing += 1
        self._buf.clear()
        self._skip_to_lf = False
        self._cand = None
        self._block = None
        self._prev = None
        self._prev_rejected = False

    # -- input ---------------------------------------------------------------------------
    def feed(self, data: bytes, stamp_ns: int | None = None) -> list[ScipReply | ScipScan]:
        out: list[ScipReply | ScipScan] = []
        if not data:
            return out
        self._buf += data
        parts = bytes(self._buf).split(b"\n")
        tail = parts.pop()
        for line in parts:
            if self._skip_to_lf:          # the end of an overlong line already dropped
                self._skip_to_lf = False
                continue
            self._line(line if len(line) <= MAX_LINE else None, stamp_ns, out)
        if len(tail) > MAX_LINE:
            if not self._skip_to_lf:
                self._line(None, stamp_ns, out)
                self._skip_to_lf = True
            tail = b""
        self._buf = bytearray(tail)
        return out

    # -- line state machine --------------------------------------------------------------
    def _line(self, line: bytes | None, stamp_ns: int | None, out: list) -> None:
        if self._block is not None:
            self._block_line(line, stamp_ns, out)
        elif self._cand is not None:
            if line == b"":                       # echo without status
                self.errors.framing += 1
                self._cand = None
            elif line is not None and _is_status(line):
                self._begin(self._cand, line)
            elif line is not None and len(line) == 1:
                self._begin(self._cand, line, legacy=True)
            else:                                 # not a status: maybe the next echo
                self.errors.framing += 1
                self._cand = line
        elif line is None:
            self.errors.framing += 1
        elif line:
            self._cand = line

    def _begin(self, echo: bytes, status: bytes, legacy: bool = False) -> None:
        self._cand = None
        self._prev = None
        self._prev_rejected = False
        m, continuous = _data_echo(echo)
        st = status[:2]
        if m is not None and not legacy:
            cmd = m.group(1).decode()
            is_scan = st == (b"99" if continuous else b"00")
            blk = _Block(echo=m.group(0), status=st, scan=is_scan, cmd=cmd,
                         bodyless=not is_scan)
            if st == b"99" and not is_scan:       # 99 on a G* command: not SCIP
                blk.bad = True
                self.errors.framing += 1
            blk.start, blk.end = int(m.group(2)), int(m.group(3))
            blk.cluster = max(1, int(m.group(4)))
            if continuous:
                blk.remaining = int(m.group(6))
            if is_scan:
                if blk.end < blk.start:
                    blk.bad = True
                    self.errors.framing += 1
                n = -(-(blk.end - blk.start + 1) // blk.cluster)
                blk.expected = max(0, n) * CHARS_PER_VALUE[cmd[1]]
        else:
            m2 = _OTHER_ECHO.search(echo)
            blk = _Block(echo=m2.group(0) if m2 else echo, status=st, scan=False,
                         legacy=legacy)
            if st == b"99":                       # only scans of M* commands carry 99
                blk.bad = True
                self.errors.framing += 1
        self._block = blk

    def _block_line(self, line: bytes | None, stamp_ns: int | None, out: list) -> None:
        blk = self._block
        assert blk is not None
        if line == b"":
            self._block = None
            self._finish(blk, stamp_ns, out)
            return
        # A status line right after an echo-like line means the current reply was cut short
        # (truncated, or its end lost to a corrupted byte): start over with the new one.
        prev = self._prev
        if (line is not None and prev is not None and _is_status(line)
                and _echo_like(prev, anywhere=self._prev_rejected)):
            self.errors.framing += 1
            self.errors.dropped += 1
            self._block = None
            self._begin(prev, line)
            return
        rejected = line is None or not self._accept(blk, line)
        if rejected and not blk.bad:
            blk.bad = True
        self._prev = line
        self._prev_rejected = rejected

    def _accept(self, blk: _Block, line: bytes) -> bool:
        """Check one line of a block and keep its payload; False (and counted) if bad."""
        if blk.bodyless:
            self.errors.framing += 1
            return False
        if blk.legacy:                            # SCIP 1.1: no checksums
            if len(blk.data) >= MAX_REPLY_LINES:
                self.errors.framing += 1
                return False
            blk.data.append(line)
            return True
        if blk.scan:
            if not line_ok(line):
                self.errors.checksum += 1
                return False
            if blk.timestamp is None:
                if len(line) != 5 or not _in_alphabet(line[:4]):
                    self.errors.framing += 1
                    return False
                blk.timestamp = decode(line[:4])
                return True
            payload = line[:-1]
            if len(payload) > MAX_DATA_PER_LINE or blk.size + len(payload) > blk.expected:
                self.errors.framing += 1
                return False
            blk.data.append(payload)
            blk.size += len(payload)
            return True
        if len(blk.data) >= MAX_REPLY_LINES:      # bound the memory a garbage stream can take
            self.errors.framing += 1
            return False
        # info lines: "KEY:value;C" (checksum excludes ';') or plain "text C"
        if len(line) >= 3 and line[-2:-1] == b";" and checksum(line[:-2]) == line[-1]:
            blk.data.append(line[:-2])
            return True
        if line_ok(line):
            blk.data.append(line[:-1])
            return True
        self.errors.checksum += 1
        return False

    def _finish(self, blk: _Block, stamp_ns: int | None, out: list) -> None:
        if blk.bad:
            self.errors.dropped += 1
            return
        if not blk.scan:
            self.replies += 1
            out.append(ScipReply(echo=blk.echo.decode("ascii", "replace"),
                                 status=blk.status.decode("ascii", "replace"),
                                 lines=[d.decode("ascii", "replace") for d in blk.data],
                                 stamp_ns=stamp_ns, legacy=blk.legacy))
            return
        if blk.timestamp is None or blk.size != blk.expected:
            self.errors.framing += 1               # truncated: lines missing
            self.errors.dropped += 1
            return
        data = b"".join(blk.data)
        if not _in_alphabet(data):
            # A byte moved by a multiple of 64 keeps the 6-bit checksum but leaves the
            # 0x30..0x6F alphabet: this catches every single-byte error the checksum misses.
            self.errors.checksum += 1
            self.errors.dropped += 1
            return
        if blk.cmd[1] == "E":
            both = decode_array(data, 3).reshape(-1, 2)
            ranges, intensity = both[:, 0].copy(), both[:, 1].copy()
        else:
            ranges, intensity = decode_array(data, CHARS_PER_VALUE[blk.cmd[1]]), None
        self.scans += 1
        out.append(ScipScan(command=blk.cmd, echo=blk.echo.decode("ascii"), start=blk.start,
                            end=blk.end, cluster=blk.cluster, remaining=blk.remaining,
                            timestamp=blk.timestamp, device_ms=self.unwrap(blk.timestamp),
                            ranges_mm=ranges, intensity=intensity, stamp_ns=stamp_ns))
