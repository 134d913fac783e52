"""SICK CoLa A (ASCII) over TCP: TiM5xx / LMS1xx scans (reference lasers.md §2).

A CoLa A telegram is ``STX "<type> <command> <args…>" ETX`` with space-separated tokens,
numbers in hex unless signed with ``+``/``-`` (decimal).  Start-up (LMS1xx node order):
``sMN SetAccessMode 03 F4724744`` (login) → ``sRN LMPscancfg`` → ``sMN LMCstartmeas`` →
poll ``sRN STlms`` until status 7 → ``sMN Run`` → ``sEN LMDscandata 1`` (subscribe); scans
then arrive as ``sSN LMDscandata …`` and are parsed by field order (version, device, status,
counters, times, I/O, frequencies, encoders, 16-bit channels each with name, scale factor
(IEEE-754 hex), offset, start angle (int32, 1/10000°), step (1/10000°), count, values; then
8-bit channels, position, name, comment, time, event info).

Angles: SICK's 0° points 90° right of forward, so ``angle_min = start − 90°`` in the laser
frame (x forward, counter-clockwise).  Ranges: ``value · scale + offset`` mm; 0 means no echo
(NaN).  RSSI1 becomes ``intensities``.

CoLa A has no checksum (TCP protects the wire): the parser is strict instead (every token
must parse, channel counts must match, every token must be consumed), so a damaged telegram is
dropped and counted unless the damage keeps the syntax (one hex digit turned into another).

CoLa B (binary, usually port 2112): ``02 02 02 02``, payload length (uint32 big-endian), payload,
XOR of the payload bytes.  The payload is ``"<type> <name> "`` and big-endian binary arguments;
``LMDscandata`` follows the field order above with the widths of SICK's telegram tables
(uint16 version/device, uint32 serial, 2 × uint8 status, uint16 counters, uint32 times, 2 × 2
uint8 I/O, uint16 layer angle, uint32 frequencies, uint16 counts, 5-char channel names, float32
scale/offset, int32 start angle, uint16 step and count).  The optional position and event blocks
are refused (their binary layout is unverified here); device name and comment are read as a
length byte and text (unverified).
"""

from __future__ import annotations

import logging
import math
import re
import struct
import time
from dataclasses import dataclass

import numpy as np

from .laser import DeviceError, LaserDriver
from .messages import ErrorCounters, LaserScan
from .transport import DeviceUrlError, Transport, parse_device_url

log = logging.getLogger(__name__)

STX, ETX = 0x02, 0x03
MAX_TELEGRAM = 1 << 16
DEFAULT_PORT = 2111
CLIENT_PASSWORD = "F4724744"   # SetAccessMode level 03 ("authorised client")


class ColaError(ValueError):
    """A CoLa telegram that cannot be parsed as what it claims to be."""


def cola_a(command: str) -> bytes:
    """Frame a CoLa A command string."""
    return b"\x02" + command.encode("ascii") + b"\x03"


class _Splitter:
    """What the CoLa A and B splitters share: the pending bytes and the error counters."""

    def __init__(self, errors: ErrorCounters | None = None) -> None:
        self.errors = errors if errors is not None else ErrorCounters()
        self.buf = bytearray()

    def reset(self) -> None:
        self.buf.clear()


class ColaAParser(_Splitter):
    """Incremental CoLa A telegram splitter: yields the text between STX and ETX as tokens.

    A new STX before the ETX means the earlier telegram was cut short: it is dropped and
    counted (``framing``); so are bytes outside telegrams and telegrams with bytes that are not
    printable ASCII or longer than :data:`MAX_TELEGRAM`.
    """

    def feed(self, data: bytes) -> list[list[bytes]]:
        buf = self.buf
        buf += data
        out: list[list[bytes]] = []
        while buf:
            s = buf.find(STX)
            if s < 0:
                self.errors.framing += 1
                buf.clear()
                break
            if s:
                self.errors.framing += 1
                del buf[:s]
            e = buf.find(ETX, 1)
            s2 = buf.find(STX, 1, e if e >= 0 else len(buf))
            if s2 >= 0:            # truncated telegram: restart at the next STX
                self.errors.framing += 1
                del buf[:s2]
                continue
            if e < 0:
                if len(buf) > MAX_TELEGRAM:
                    self.errors.framing += 1
                    buf.clear()
                break
            body = bytes(buf[1:e])
            del buf[:e + 1]
            if not body or not _printable(body):
                self.errors.framing += 1
                continue
            out.append(body.split(b" "))
        return out


_NOT_PRINTABLE = re.compile(rb"[^\x20-\x7e]")


def _printable(b: bytes) -> bool:
    return _NOT_PRINTABLE.search(b) is None


_SPY_PREFIX = re.compile(r"(?:spy\+)*")
# a TCP URL whose host has no port after it (the port goes at the end of the match)
_HOST_WITHOUT_PORT = re.compile(r"(?:tcp|socket)://(?:\[[^\]]*\]|[^:/?#\[\]]+)(?=[/?#]|$)",
                                re.IGNORECASE)


def _with_default_port(url: str) -> tuple[str, int | None]:
    """``host``, ``tcp://host`` (with ``spy+``, options) → ``tcp://host:2111``, and the URL's TCP
    port.  A name without ``://`` is a host: CoLa runs on TCP here.  The URL is checked by
    ``parse_device_url`` (a malformed port raises its one-line ``DeviceUrlError``, a
    ValueError); a scheme the transport does not know is left for ``open`` to refuse."""
    if url.startswith("spy://"):            # the older spelling of spy+, as open_transport
        url = "spy+" + url[6:]
    spy = _SPY_PREFIX.match(url).group()
    rest = url[len(spy):]
    if "://" not in rest:
        rest = "tcp://" + rest
    if m := _HOST_WITHOUT_PORT.match(rest):
        rest = f"{rest[:m.end()]}:{DEFAULT_PORT}{rest[m.end():]}"
    try:
        return spy + rest, parse_device_url(spy + rest).port
    except DeviceUrlError as exc:
        if spy + rest == url:
            raise
        raise DeviceUrlError(f"{url}: read as {exc}") from None


_HEX = frozenset(b"0123456789ABCDEFabcdef")


def _int(tok: bytes, bits: int = 32, signed: bool = False) -> int:
    """A CoLa A number: hex, or decimal with an explicit sign."""
    if not tok or len(tok) > 12:
        raise ColaError(f"bad number token {tok[:16]!r}")
    if tok[:1] in (b"+", b"-"):
        if not tok[1:].isdigit():
            raise ColaError(f"bad decimal token {tok!r}")
        return int(tok)
    if len(tok) > bits // 4 or not _HEX.issuperset(tok):
        raise ColaError(f"bad hex token {tok!r}")
    v = int(tok, 16)
    if signed and v >= 1 << (bits - 1):
        v -= 1 << bits
    return v


def _float(tok: bytes) -> float:
    if len(tok) != 8 or not _HEX.issuperset(tok):
        raise ColaError(f"bad float token {tok!r}")
    v = struct.unpack(">f", bytes.fromhex(tok.decode()))[0]
    if not math.isfinite(v):
        raise ColaError(f"non-finite float {tok!r}")
    return v


def _hex_array(tokens: list[bytes], bits: int) -> np.ndarray:
    """Vectorised strict parse of hex tokens of at most bits/4 digits."""
    width = bits // 4
    if not tokens:
        return np.zeros(0, np.int64)
    lens = np.fromiter((len(t) for t in tokens), np.int64, len(tokens))
    if lens.min() < 1 or lens.max() > width:
        raise ColaError("bad value token length")
    padded = b"".join(t.rjust(width, b"0") for t in tokens)
    a = np.frombuffer(padded, np.uint8).reshape(-1, width).astype(np.int64)
    digit = np.where(a <= ord("9"), a - ord("0"), (a | 0x20) - ord("a") + 10)
    ok = ((a >= ord("0")) & (a <= ord("9"))) | (((a | 0x20) >= ord("a")) & ((a | 0x20) <= ord("f")))
    if not ok.all():
        raise ColaError("non-hex character in values")
    return digit @ (16 ** np.arange(width - 1, -1, -1))


@dataclass
class Channel:
    name: str
    scale: float
    offset: float
    start_angle: float   # degrees, SICK frame
    step: float          # degrees
    values: np.ndarray


@dataclass
class ScanData:
    """The fields of an ``LMDscandata`` telegram that a scan needs."""

    telegram_counter: int
    scan_counter: int
    time_since_start_us: int
    scan_frequency: float     # Hz
    channels16: list[Channel]
    channels8: list[Channel]

    def channel(self, name: str) -> Channel | None:
        for ch in self.channels16 + self.channels8:
            if ch.name == name:
                return ch
        return None


def parse_scandata(tokens: list[bytes]) -> ScanData:
    """Parse ``sRA|sSN LMDscandata …`` by field order; raises ColaError unless every token
    fits the layout and all are consumed."""
    if len(tokens) < 22 or tokens[0] not in (b"sRA", b"sSN") or tokens[1] != b"LMDscandata":
        raise ColaError("not an LMDscandata telegram")
    i = 2

    def take(n: int = 1) -> list[bytes]:
        nonlocal i
        if i + n > len(tokens):
            raise ColaError("LMDscandata telegram ends early")
        out = tokens[i:i + n]
        i += n
        return out

    _int(take()[0], 16)                       # version
    _int(take()[0], 16)                       # device number
    _int(take()[0], 32)                       # serial number
    for t in take(2):                         # device status
        _int(t, 8)
    tele = _int(take()[0], 16)
    scan = _int(take()[0], 16)
    t_start = _int(take()[0], 32)
    _int(take()[0], 32)                       # time of transmission
    for t in take(5):                         # inputs (2), outputs (2), reserved
        _int(t, 16)
    freq = _int(take()[0], 32) / 100.0
    _int(take()[0], 32)                       # measurement frequency
    n_enc = _int(take()[0], 16)
    if n_enc > 8:
        raise ColaError(f"implausible encoder count {n_enc}")
    for _ in range(n_enc):
        _int(take()[0], 32)
        _int(take()[0], 16)

    def channels(bits: int) -> list[Channel]:
        n = _int(take()[0], 16)
        if n > 8:
            raise ColaError(f"implausible channel count {n}")
        out = []
        for _ in range(n):
            name = take()[0]
            if not (name[:4] in (b"DIST", b"RSSI", b"ANGL") and name[4:].isdigit()):
                raise ColaError(f"unknown channel {name!r}")
            scale = _float(take()[0])
            offset = _float(take()[0])
            start = _int(take()[0], 32, signed=True) / 1e4
            step = _int(take()[0], 16) / 1e4
            count = _int(take()[0], 16)
            if count == 0 or count > 10000 or step == 0:
                raise ColaError(f"implausible channel {name!r}: {count} values, step {step}")
            vals = _hex_array(take(count), bits)
            out.append(Channel(name.decode(), scale, offset, start, step, vals))
        return out

    ch16 = channels(16)
    ch8 = channels(8)
    if _int(take()[0], 8):                    # position block
        take(7)
    if _int(take()[0], 8):                    # device name
        n = _int(take()[0], 8)
        name = take()[0]
        if len(name) != n:
            raise ColaError("device name length mismatch")
    if _int(take()[0], 8):                    # comment
        n = _int(take()[0], 8)
        take()
    if _int(take()[0], 8):                    # time stamp: Y M D h m s us
        for t in take(7):
            _int(t, 32)
    if _int(take()[0], 8):                    # event info
        take(4)
    if i != len(tokens):
        raise ColaError(f"{len(tokens) - i} unexpected tokens after LMDscandata")
    return ScanData(tele, scan, t_start, freq, ch16, ch8)


def scan_from_data(data: ScanData, stamp_ns: int) -> LaserScan:
    """A LaserScan from DIST1 (and RSSI1): metres, NaN for no echo, SICK frame → laser frame."""
    dist = data.channel("DIST1")
    if dist is None:
        raise ColaError("LMDscandata without DIST1")
    mm = dist.values * dist.scale + dist.offset
    # raw values below 16 are codes, not ranges: 0 no echo, 1 dazzled, 2-15 reserved
    ranges = np.where(dist.values < 16, np.nan, mm / 1000.0)
    rssi = data.channel("RSSI1")
    inten = None
    if rssi is not None and len(rssi.values) == len(ranges):
        inten = rssi.values * rssi.scale + rssi.offset
    return LaserScan(
        seq=0, stamp_ns=stamp_ns,
        angle_min=math.radians(dist.start_angle) - math.pi / 2,
        angle_increment=math.radians(dist.step), ranges=ranges,
        range_min=0.05, range_max=float("inf"),
        scan_time=1.0 / data.scan_frequency if data.scan_frequency > 0 else 0.0,
        intensities=inten, device_stamp=data.scan_counter)


# -- CoLa B -----------------------------------------------------------------------------------
COLA_B_MAGIC = b"\x02\x02\x02\x02"


def _xor(data: bytes) -> int:
    return int(np.bitwise_xor.reduce(np.frombuffer(data, np.uint8))) if data else 0


def cola_b(payload: bytes) -> bytes:
    """Frame a CoLa B payload: magic, length (uint32 BE), payload, XOR checksum."""
    return COLA_B_MAGIC + len(payload).to_bytes(4, "big") + payload + bytes([_xor(payload)])


class ColaBParser(_Splitter):
    """Incremental CoLa B splitter: payloads with a good XOR; bad ones dropped and counted
    (``checksum``), bytes outside frames counted (``framing``); sliding resumes one byte on."""

    def feed(self, data: bytes) -> list[list[bytes]]:
        """Payloads split as ``[type, name, binary rest]``."""
        buf = self.buf
        buf += data
        out: list[list[bytes]] = []
        while buf:
            i = buf.find(COLA_B_MAGIC)
            if i < 0:
                keep = len(buf) - len(buf.rstrip(b"\x02"))
                if len(buf) > keep:
                    self.errors.framing += 1
                del buf[:len(buf) - min(keep, 3)]
                break
            if i:
                self.errors.framing += 1
                del buf[:i]
            if len(buf) < 8:
                break
            n = int.from_bytes(buf[4:8], "big")
            if n == 0 or n > MAX_TELEGRAM * 4:
                self.errors.framing += 1
                del buf[:1]
                continue
            if len(buf) < 9 + n:
                break
            payload = bytes(buf[8:8 + n])
            if _xor(payload) != buf[8 + n]:
                self.errors.checksum += 1
                del buf[:1]
                continue
            del buf[:9 + n]
            parts = payload.split(b" ", 2)
            if len(parts) < 2 or not _printable(parts[0]):
                self.errors.framing += 1
                continue
            out.append(parts)
        return out


class _Reader:
    def __init__(self, data: bytes) -> None:
        self.data, self.i = data, 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.i + size > len(self.data):
            raise ColaError("binary LMDscandata ends early")
        out = struct.unpack_from(fmt, self.data, self.i)
        self.i += size
        return out

    def raw(self, n: int) -> bytes:
        if self.i + n > len(self.data):
            raise ColaError("binary LMDscandata ends early")
        self.i += n
        return self.data[self.i - n:self.i]


def parse_scandata_b(data: bytes) -> ScanData:
    """Parse the binary arguments of ``sRA|sSN LMDscandata`` (after the name and its space);
    raises ColaError unless the layout fits and every byte is consumed."""
    r = _Reader(data)
    (_version, _device, _serial, _s1, _s2, tele, scan, t_start, _t_tx, _i1, _i2, _o1, _o2,
     _layer, freq, _mfreq, n_enc) = r.take(">HHIBBHHIIBBBBHIIH")
    if n_enc > 8:
        raise ColaError(f"implausible encoder count {n_enc}")
    r.take(">" + "IH" * n_enc)

    def channels(dtype: str) -> list[Channel]:
        (n,) = r.take(">H")
        if n > 8:
            raise ColaError(f"implausible channel count {n}")
        out = []
        for _ in range(n):
            name = r.raw(5)
            if not (name[:4] in (b"DIST", b"RSSI", b"ANGL", b"REFL") and name[4:].isdigit()):
                raise ColaError(f"unknown channel {name!r}")
            scale, offset, start, step, count = r.take(">ffiHH")
            if not (math.isfinite(scale) and math.isfinite(offset)) or count == 0 or step == 0:
                raise ColaError(f"implausible channel {name!r}")
            size = np.dtype(dtype).itemsize
            vals = np.frombuffer(r.raw(size * count), dtype).astype(np.int64)
            out.append(Channel(name.decode(), scale, offset, start / 1e4, step / 1e4, vals))
        return out

    ch16 = channels(">u2")
    ch8 = channels("u1")
    (position,) = r.take(">H")
    if position:
        raise ColaError("LMDscandata position block not supported")
    (has_name,) = r.take(">H")
    if has_name:
        r.raw(r.take(">B")[0])
    (has_comment,) = r.take(">H")
    if has_comment:
        r.raw(r.take(">B")[0])
    (has_time,) = r.take(">H")
    if has_time:
        r.take(">HBBBBBI")
    (event,) = r.take(">H")
    if event:
        raise ColaError("LMDscandata event block not supported")
    if r.i != len(data):
        raise ColaError(f"{len(data) - r.i} unexpected bytes after LMDscandata")
    return ScanData(tele, scan, t_start, freq / 100.0, ch16, ch8)


class ColaDriver(LaserDriver):
    """SICK TiM5xx / LMS1xx over CoLa A or B on TCP (``tcp://host:2111``).

    ``protocol``: "A" (ASCII), "B" (binary) or "auto" (B on port 2112, else A).
    """

    model = "cola"

    def __init__(self, device: str | Transport, timeout: float = 0.5, *,
                 password: str = CLIENT_PASSWORD, ready_timeout: float = 5.0,
                 protocol: str = "auto", command_timeout: float = 1.0, **kw) -> None:
        if isinstance(device, str):
            device, port = _with_default_port(device)
        else:                       # an open transport: its URL says the port, if any
            try:
                port = parse_device_url(device.url).port
            except DeviceUrlError:
                port = None
        super().__init__(device, timeout, **kw)
        protocol = protocol.upper()
        if protocol == "AUTO":
            protocol = "B" if port == 2112 else "A"
        if protocol not in ("A", "B"):
            raise ValueError(f"CoLa protocol must be 'A', 'B' or 'auto', not {protocol!r}")
        self.protocol = protocol
        self.command_timeout = command_timeout
        self.password = password
        self.ready_timeout = ready_timeout
        self.parser = ColaAParser(self.errors) if protocol == "A" else ColaBParser(self.errors)
        self._pending: list[tuple[list[bytes], int]] = []
        self.scan_config: list[bytes] = []
        self.subscribed = False

    # -- request / reply --------------------------------------------------------------------
    def _telegrams(self, timeout: float) -> list[tuple[list[bytes], int]]:
        if self._pending:
            out, self._pending = self._pending, []
            return out
        data = self.transport.read(65536, timeout)
        if not data:
            return []
        stamp = time.monotonic_ns()
        return [(t, stamp) for t in self.parser.feed(data)]

    def command(self, text: str, timeout: float | None = None, binary: bytes | None = None
                ) -> list[bytes]:
        """Send ``sXN name args``; return the reply tokens (``sXA name …``; in CoLa B
        ``[type, name, binary rest]``).  In CoLa B ``text`` is the type and name and ``binary``
        the arguments.  ``sFA`` (error) raises DeviceError; scans meanwhile are kept."""
        kind, name = text.split(" ", 2)[:2]
        want = {b"sRN": b"sRA", b"sWN": b"sWA", b"sMN": b"sAN", b"sEN": b"sEA"}[kind.encode()]
        if self.protocol == "A":
            self.transport.write(cola_a(text))
        else:
            args = b"" if binary is None else b" " + binary
            self.transport.write(cola_b(text.encode("ascii") + args))
        deadline = time.monotonic() + (self.command_timeout if timeout is None else timeout)
        keep: list[tuple[list[bytes], int]] = []
        try:
            while (left := deadline - time.monotonic()) > 0:
                for toks, stamp in self._telegrams(left):
                    if toks[0] == want and len(toks) > 1 and toks[1] == name.encode():
                        return toks
                    if toks[0] == b"sFA":
                        self.errors.device += 1
                        code = (toks[1].decode("ascii", "replace") if self.protocol == "A"
                                else str(int.from_bytes(b" ".join(toks[1:]), "big")))
                        raise DeviceError(f"CoLa error sFA {code} for {text!r}")
                    if toks[0] == b"sSN":
                        keep.append((toks, stamp))
        finally:
            self._pending = keep + self._pending
        self.errors.timeout += 1
        raise DeviceError(f"no reply to {text!r}")

    # -- life cycle ---------------------------------------------------------------------------
    def _start(self) -> None:
        self.parser.reset()
        self._pending = []
        self.transport.reset_input()
        b = self.protocol == "B"
        if b:
            r = self.command("sMN SetAccessMode",
                             binary=struct.pack(">BI", 3, int(self.password, 16)))
        else:
            r = self.command(f"sMN SetAccessMode 03 {self.password}")
        if not self._true(r):
            raise DeviceError("CoLa login (SetAccessMode 03) refused")
        self.scan_config = self.command("sRN LMPscancfg")[2:]
        self.command("sMN LMCstartmeas")
        deadline = time.monotonic() + self.ready_timeout
        while True:
            st = self.command("sRN STlms")
            if len(st) > 2 and (st[2][:2] == b"\x00\x07" if b else st[2] == b"7"):
                break
            if time.monotonic() > deadline:
                raise DeviceError(f"device not ready (STlms {st[2:3]!r})")
            time.sleep(0.05)
        self.command("sMN Run")
        r = (self.command("sEN LMDscandata", binary=b"\x01") if b
             else self.command("sEN LMDscandata 1"))
        if not self._true(r):
            raise DeviceError("LMDscandata subscription refused")
        self.subscribed = True

    def _true(self, reply: list[bytes]) -> bool:
        """The result flag of a reply: last token "1" (A) or first argument byte 1 (B)."""
        if self.protocol == "A":
            return reply[-1] == b"1"
        return len(reply) > 2 and reply[2][:1] == b"\x01"

    def _stop(self) -> None:
        if self.subscribed:
            self.subscribed = False
            if self.protocol == "B":
                self.command("sEN LMDscandata", binary=b"\x00")
            else:
                self.command("sEN LMDscandata 0")

    def _parse(self, toks: list[bytes]) -> ScanData:
        if self.protocol == "A":
            return parse_scandata(toks)
        if len(toks) != 3:
            raise ColaError("LMDscandata without arguments")
        return parse_scandata_b(toks[2])

    def request_scan(self, timeout: float = 2.0) -> LaserScan:
        """One scan on request (``sRN LMDscandata``)."""
        toks = self.command("sRN LMDscandata", timeout)
        return scan_from_data(self._parse(toks), time.monotonic_ns())

    def _receive_scan(self, timeout: float) -> LaserScan | None:
        deadline = time.monotonic() + timeout
        while True:
            tels = self._telegrams(max(0.0, deadline - time.monotonic()))
            for k, (toks, stamp) in enumerate(tels):
                if toks[:2] != [b"sSN", b"LMDscandata"]:
                    continue
                try:
                    scan = scan_from_data(self._parse(toks), stamp)
                except ColaError as exc:
                    self.errors.framing += 1
                    log.debug("%s: dropped scan: %s", self.url, exc)
                    continue
                self._pending = tels[k + 1:] + self._pending
                return scan
            if time.monotonic() >= deadline:
                return None
