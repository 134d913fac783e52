"""Differential-drive base whose motor controller speaks Modbus (TCP or RTU), via pymodbus.

The driver yields what the controller measures, :class:`~cgamap.drivers.messages.WheelTicks`
(unwrapped encoder counts, wheel speeds, status word, e-stop bit); ``mapping.odometry`` turns
ticks into poses.  The register map is configuration (:class:`RegisterMap`); the default map,
served by the twin ``cgamap sim-device modbus-base``, is:

=====================  =====  =====  ======  ==========  ===============================
item                   table  addr   words   signed      scaling
=====================  =====  =====  ======  ==========  ===============================
left encoder count     input  0      2 (32)  yes         ticks (wraps at 2^32)
right encoder count    input  2      2 (32)  yes         ticks
left wheel speed       input  4      2 (32)  yes         0.001 rad/s per count (mrad/s)
right wheel speed      input  6      2 (32)  yes         0.001 rad/s per count
status word            input  8      1 (16)  no          bit 0 = e-stop pressed
left speed set-point   hold.  0      2 (32)  yes         0.001 rad/s per count
right speed set-point  hold.  2      2 (32)  yes         0.001 rad/s per count
=====================  =====  =====  ======  ==========  ===============================

32-bit values are big-endian words (high word first, the Modbus convention) unless a field says
``word_order: little``.  Encoder counters wrap: the driver unwraps the difference between two
reads modulo 2^bits (so the base must not move more than half the counter range between two
polls: 2^31 ticks at 32 bits, 32768 at 16 bits).

URLs: ``tcp://host:port`` (Modbus TCP), ``rtu+tcp://host:port`` (RTU framing over TCP),
``serial:///dev/ttyUSB0`` or a plain path (RTU on a serial port or pty), bare ``host:port``
(Modbus TCP); query options
``unit=`` / ``device_id=`` (default 1), ``baudrate=`` / ``baud=`` (default 115200).

Polling runs on absolute deadlines ``t0 + k / rate``: a slow read delays one sample, not all the
ones after it; slots missed while a read overran are skipped and counted (``dropped``).  A
missing or late reply is a counted ``timeout`` after at most ``timeout_s``; the driver then waits
one more timeout and drains the input, so a late reply is never taken for the next one.
Exception responses count as ``device``, a lost connection as ``disconnects`` (reopened after
``reconnect_s``; reads in between count as ``dropped``).  Writing wheel-speed set-points needs
``allow_setpoints: true`` (off by default).

Stamps: the controller samples its counters when the request arrives, so a read's ``stamp_ns``
is the midpoint between sending the request and receiving the reply of the block holding
``left_ticks`` (not the instant all blocks were back), and ``stamp_uncertainty_ns`` is half that
round trip: the sampling instant lies within +- the uncertainty of the stamp.  The instants come
from pymodbus's ``trace_packet`` hook (bytes handed to / taken from the transport), else from
around the client call.  On a serial line the reply frame is longer on the wire than the
request; the stamp moves back by half the difference (:func:`rtu_wire_skew_ns`).
"""

from __future__ import annotations

import logging
import math
import os
import select
import socket
import termios
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any

from .messages import ErrorCounters, WheelTicks
from .pacing import paced_reads
from .transport import parse_device_url

log = logging.getLogger(__name__)


# -- register coding (pure, unit-tested) ------------------------------------------------------

def decode_registers(regs: Sequence[int], signed: bool = True, word_order: str = "big") -> int:
    """Integer from 16-bit registers; ``word_order`` "big" = most significant word first."""
    words = list(regs) if word_order == "big" else list(regs)[::-1]
    value = 0
    for w in words:
        value = (value << 16) | (int(w) & 0xFFFF)
    bits = 16 * len(words)
    if signed and value >= 1 << (bits - 1):
        value -= 1 << bits
    return value


def encode_registers(value: int, words: int, word_order: str = "big") -> list[int]:
    """16-bit registers of an integer (two's complement when negative), ``words`` long."""
    bits = 16 * words
    v = int(value) & ((1 << bits) - 1)
    regs = [(v >> (16 * (words - 1 - i))) & 0xFFFF for i in range(words)]
    return regs if word_order == "big" else regs[::-1]


def unwrap_delta(raw_now: int, raw_prev: int, bits: int) -> int:
    """Signed change of a wrapping counter: the difference modulo 2^bits in [-2^(b-1), 2^(b-1))."""
    half = 1 << (bits - 1)
    return ((raw_now - raw_prev + half) % (1 << bits)) - half


@dataclass(frozen=True)
class RegisterField:
    """One value in the controller's register space."""

    address: int
    words: int = 2                 # 1 = 16-bit, 2 = 32-bit
    signed: bool = True
    word_order: str = "big"        # "big": high word first; "little": low word first
    scale: float = 1.0             # physical value = raw * scale
    table: str = "input"           # "input" (FC 4) or "holding" (FC 3 / FC 16)

    def __post_init__(self) -> None:
        if self.words not in (1, 2, 4):
            raise ValueError(f"register field at {self.address}: words must be 1, 2 or 4")
        if self.word_order not in ("big", "little"):
            raise ValueError(f"register field at {self.address}: word_order big or little")
        if self.table not in ("input", "holding"):
            raise ValueError(f"register field at {self.address}: table input or holding")

    @property
    def bits(self) -> int:
        return 16 * self.words

    def raw(self, block: Sequence[int], block_start: int) -> int:
        i = self.address - block_start
        return decode_registers(block[i:i + self.words], self.signed, self.word_order)

    def encode(self, physical: float) -> list[int]:
        raw = round(physical / self.scale)
        lo = -(1 << (self.bits - 1)) if self.signed else 0
        hi = (1 << (self.bits - 1)) - 1 if self.signed else (1 << self.bits) - 1
        if not lo <= raw <= hi:
            raise ValueError(f"register {self.address}: {physical} does not fit {self.bits} bits")
        return encode_registers(raw, self.words, self.word_order)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | RegisterField) -> RegisterField:
        if isinstance(d, RegisterField):
            return d
        known = {f.name for f in fields(cls)}
        bad = set(d) - known
        if bad:
            raise ValueError(f"register field: unknown keys {sorted(bad)}")
        return cls(**d)


def rtu_wire_skew_ns(reply_registers: int, baudrate: int, bits_per_char: int = 10) -> int:
    """How far the request/reply midpoint lies after the sampling instant on an RTU line.

    The controller samples when the last request byte arrived (8 bytes for FC 3/4) and the
    driver sees the reply once its last byte is in (5 + 2n bytes): the midpoint is late by half
    the difference of the two frames' times on the wire (8N1: 10 bits per byte)."""
    request_bytes, reply_bytes = 8, 5 + 2 * reply_registers
    return (reply_bytes - request_bytes) * bits_per_char * 1_000_000_000 // (2 * baudrate)


_READ_FIELDS = ("left_ticks", "right_ticks", "left_speed", "right_speed", "status")


@dataclass(frozen=True)
class RegisterMap:
    """Where the controller keeps each item (see the module docstring for the default)."""

    left_ticks: RegisterField = RegisterField(0)
    right_ticks: RegisterField = RegisterField(2)
    left_speed: RegisterField | None = RegisterField(4, scale=0.001)
    right_speed: RegisterField | None = RegisterField(6, scale=0.001)
    status: RegisterField | None = RegisterField(8, words=1, signed=False)
    estop_bit: int | None = 0
    left_setpoint: RegisterField | None = RegisterField(0, table="holding", scale=0.001)
    right_setpoint: RegisterField | None = RegisterField(2, table="holding", scale=0.001)

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> RegisterMap:
        """Default map with the given items replaced (``None`` drops an optional item)."""
        if not d:
            return cls()
        known = {f.name for f in fields(cls)}
        bad = set(d) - known
        if bad:
            raise ValueError(f"register map: unknown items {sorted(bad)}")
        kw = {k: (v if k == "estop_bit" or v is None else RegisterField.from_dict(v))
              for k, v in d.items()}
        return replace(cls(), **kw)

    def read_blocks(self) -> list[tuple[str, int, int]]:
        """(table, start, count) spans covering the read items: one request per table."""
        spans: dict[str, tuple[int, int]] = {}
        for name in _READ_FIELDS:
            f = getattr(self, name)
            if f is None:
                continue
            lo, hi = spans.get(f.table, (f.address, f.address + f.words))
            spans[f.table] = (min(lo, f.address), max(hi, f.address + f.words))
        return [(t, lo, hi - lo) for t, (lo, hi) in sorted(spans.items())]


@dataclass
class ModbusBaseConfig:
    """Driver configuration; geometry is carried here for the caller (mapping.odometry)."""

    url: str = "tcp://127.0.0.1:502"
    device_id: int | None = None       # None: from the URL (unit=), else 1
    rate_hz: float = 50.0
    timeout_s: float = 0.1
    baudrate: int | None = None        # None: from the URL, else 115200
    registers: RegisterMap = field(default_factory=RegisterMap)
    wheel_radius: float = 0.05
    track_width: float = 0.30
    ticks_per_rev: float = 4096.0
    left_sign: int = 1
    right_sign: int = 1
    reconnect_s: float = 1.0           # wait this long before reopening a lost connection
    allow_setpoints: bool = False
    max_wheel_speed: float = 30.0      # rad/s: set-points beyond this are refused

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> ModbusBaseConfig:
        """From a config mapping; accepts ``rate`` for rate_hz, ``track`` for track_width and
        a ``params`` sub-mapping (as in config/robot.yaml)."""
        d = dict(d)
        d.update(d.pop("params", None) or {})
        alias = {"rate": "rate_hz", "track": "track_width", "timeout": "timeout_s"}
        d = {alias.get(k, k): v for k, v in d.items()}
        known = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in known}
        if "registers" in kw:
            kw["registers"] = RegisterMap.from_dict(kw["registers"])
        return cls(**kw)


class ModbusBaseError(Exception):
    """The base could not be opened, a request was refused before sending, or an answered
    request left the driver in a state it cannot read from (an internal fault)."""


class ModbusBaseConfigError(ModbusBaseError, ValueError):
    """The URL or configuration is unusable (bad scheme, unit id, baud rate)."""


def _int_option(url: str, name: str, value: Any) -> int:
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ModbusBaseConfigError(f"{url}: {name} {value!r} is not a whole number") from None


# URL scheme -> how the client talks: Modbus TCP, RTU framing over TCP, or RTU on a serial line
_KINDS = {"tcp": "tcp", "modbus+tcp": "tcp", "rtu+tcp": "rtu+tcp", "socket": "rtu+tcp",
          "serial": "rtu", "rtu": "rtu"}


class ModbusBase:
    """Poll a Modbus motor controller for wheel encoder counts.

    ``client`` may be injected (any object with pymodbus's sync client methods) for tests.
    """

    def __init__(self, config: ModbusBaseConfig, client: Any | None = None) -> None:
        self.config = config
        self.errors = ErrorCounters()
        self._client = client
        u = parse_device_url(config.url, _KINDS, ModbusBaseConfigError)
        self._kind, self._where, self._port = _KINDS[u.scheme], u.host or u.path, u.port
        url, opts = config.url, u.options
        self.device_id = _int_option(url, "unit id", config.device_id if config.device_id
                                     is not None else opts.get("unit", opts.get("device_id", 1)))
        # 0 is broadcast (no replies: reads impossible); 248..255 are reserved
        if not 1 <= self.device_id <= 247:
            raise ModbusBaseConfigError(f"{url}: Modbus unit id must be 1..247 (0 is broadcast, "
                                        f"no replies), got {self.device_id}")
        self.baudrate = _int_option(url, "baud rate", config.baudrate if config.baudrate
                                    is not None else u.baud or 115200)
        if self.baudrate <= 0:
            raise ModbusBaseConfigError(f"{url}: baud rate must be positive, got {self.baudrate}")
        self._prev_raw: dict[str, int] = {}
        self._count: dict[str, int] = {}
        self._seq = 0
        self._connected = False
        self._failing = False
        self._answered = False     # any reply since open: failures before it are the caller's
        self._next_connect = 0.0
        # (sent, received) monotonic ns of the last transaction, as the trace hook saw them
        self._wire: list[int | None] = [None, None]
        # (sent, received) of the last answered transaction; read() clears it per request
        self.last_window_ns: tuple[int, int] | None = None

    # -- connection ---------------------------------------------------------------------
    def _make_client(self) -> Any:
        from pymodbus import FramerType
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient

        # pymodbus logs every failed transaction at ERROR; the driver counts them instead.
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        t, tr = self.config.timeout_s, self._trace_packet
        if self._kind == "tcp":
            return ModbusTcpClient(self._where, port=self._port, timeout=t, retries=0,
                                   trace_packet=tr)
        if self._kind == "rtu+tcp":
            # the TCP client with the RTU framer: the serial client on a socket:// URL sees
            # in_waiting as 0 or 1 and takes the reply a byte per poll (~50 ms a read)
            return ModbusTcpClient(self._where, port=self._port, framer=FramerType.RTU,
                                   timeout=t, retries=0, trace_packet=tr)
        return ModbusSerialClient(self._where, framer=FramerType.RTU, baudrate=self.baudrate,
                                  timeout=t, retries=0, trace_packet=tr)

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        """pymodbus hook, called with each frame sent and each received chunk: notes when the
        request went out and when the first reply bytes came in (the stamp's window)."""
        now = time.monotonic_ns()
        if sending:
            self._wire = [now, None]
        elif self._wire[1] is None:
            self._wire[1] = now
        return data

    def open(self) -> ModbusBase:
        """Connect; raises :class:`ModbusBaseError` (one line) when the device is not there."""
        if self._client is None:
            self._client = self._make_client()
        if not self._client.connect():
            raise ModbusBaseError(f"{self.config.url}: cannot connect{self._why_not()}")
        self._connected = True
        self._answered = False
        return self

    def _why_not(self) -> str:
        """Why connecting failed, as far as the OS says (pymodbus only returns False)."""
        if self._kind == "rtu":
            if not os.path.exists(self._where):
                return " (no such device)"
            if os.path.isdir(self._where):
                return " (is a directory, not a serial port)"
            if not os.access(self._where, os.R_OK | os.W_OK):
                return " (permission denied: is the user in the dialout group?)"
            return ""
        try:
            with socket.create_connection((self._where, self._port),
                                          timeout=self.config.timeout_s):
                return ""
        except OSError as exc:
            return f" ({exc.strerror or exc})"

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        self._connected = False

    def __enter__(self) -> ModbusBase:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _drain(self) -> None:
        """After a timeout: wait one more timeout, then drop whatever arrived (late replies)."""
        time.sleep(self.config.timeout_s)
        sock = getattr(self._client, "socket", None)
        if sock is None:
            return
        try:
            if hasattr(sock, "reset_input_buffer"):        # pyserial port
                sock.reset_input_buffer()
            else:                                           # TCP socket
                while select.select([sock], [], [], 0)[0]:
                    if not sock.recv(4096):
                        break
        except (OSError, termios.error):
            pass

    # -- transactions -------------------------------------------------------------------
    def _log_failure(self, what: str, exc: Exception) -> None:
        """Warn once when a device that answered starts failing; the counters carry the rest.
        One that never answered is reported by the caller (poll's silence error, the CLI's
        line, the supervisor's restart): a warning here would say the same thing twice."""
        level = logging.WARNING if self._answered and not self._failing else logging.DEBUG
        self._failing = True
        log.log(level, "%s: %s (%s)", self.config.url, what, exc)

    def _request(self, fn: str, *args: Any, **kw: Any) -> Any | None:
        """One Modbus transaction; None (and a counted error) if it failed."""
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        if self._client is None:
            raise ModbusBaseError(f"{self.config.url}: not open")
        t_call = time.monotonic_ns()
        try:
            if not self._connected:
                if time.monotonic() < self._next_connect:   # backing off: a missed sample
                    self.errors.dropped += 1
                    return None
                if not self._client.connect():
                    raise ConnectionException("reconnect failed")
                self._connected = True
            rr = getattr(self._client, fn)(*args, device_id=self.device_id, **kw)
        except (ConnectionException, OSError, termios.error) as exc:  # refused, reset, gone
            self.errors.disconnects += 1
            self._log_failure("connection lost", exc)
            try:
                self._client.close()
            except (OSError, termios.error):
                pass
            self._connected = False
            # reopening a vanished path at once could grab whatever device gets its name next
            self._next_connect = time.monotonic() + self.config.reconnect_s
            return None
        except ModbusIOException as exc:
            self.errors.timeout += 1
            self._log_failure("no reply", exc)
            self._drain()
            return None
        t_back = time.monotonic_ns()
        self._failing = False
        self._answered = True
        sent, got = self._wire
        # the hook's instants leave out encoding, decoding and a reconnect; an injected client
        # without the hook is timed around the call
        if sent is not None and got is not None and t_call <= sent <= got <= t_back:
            self.last_window_ns = (sent, got)
        else:
            self.last_window_ns = (t_call, t_back)
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            if code is None:  # some pymodbus paths return an error object for timeouts
                self.errors.timeout += 1
                self._drain()
            else:
                self.errors.device += 1
                log.info("%s: exception response %s", self.config.url, code)
            return None
        return rr

    def read(self) -> WheelTicks | None:
        """Read the controller once: a WheelTicks, or None after a counted error."""
        regmap = self.config.registers
        blocks: dict[str, tuple[int, list[int]]] = {}
        windows: dict[str, tuple[int, int]] = {}
        for table, start, count in regmap.read_blocks():
            fn = "read_input_registers" if table == "input" else "read_holding_registers"
            self.last_window_ns = None      # this request's window, never an earlier one's
            rr = self._request(fn, start, count=count)
            if rr is None:
                return None
            if len(rr.registers) < count:
                self.errors.framing += 1
                return None
            blocks[table] = (start, list(rr.registers))
            # every answered request sets its window; a reply without one cannot be stamped
            # (a real check: an assert would vanish under python -O and fail later, unclear)
            if self.last_window_ns is None:
                raise ModbusBaseError(f"{self.config.url}: {fn} {start}+{count} answered but "
                                      "left no request/reply window to stamp the ticks with")
            windows[table] = self.last_window_ns
        # The counters were sampled while the tick block's request was at the controller.  A
        # map that puts right_ticks in another table (block) than left_ticks gets the left
        # block's instant: the two samples are one request apart, and one stamp has to do.
        tick_table = regmap.left_ticks.table
        sent, got = windows[tick_table]
        stamp = (sent + got) // 2
        if self._kind == "rtu":
            stamp -= rtu_wire_skew_ns(len(blocks[tick_table][1]), self.baudrate)
        uncertainty = (got - sent + 1) // 2

        def value(name: str) -> int | None:
            f = getattr(regmap, name)
            if f is None:
                return None
            start, regs = blocks[f.table]
            return f.raw(regs, start)

        for name in ("left_ticks", "right_ticks"):
            raw = value(name)
            f = getattr(regmap, name)
            if name not in self._prev_raw:
                self._count[name] = raw
            else:
                self._count[name] += unwrap_delta(raw, self._prev_raw[name], f.bits)
            self._prev_raw[name] = raw
        speeds = [None if getattr(regmap, n) is None else value(n) * getattr(regmap, n).scale
                  for n in ("left_speed", "right_speed")]
        status = value("status")
        estop = bool(status is not None and regmap.estop_bit is not None
                     and status >> regmap.estop_bit & 1)
        self._seq += 1
        return WheelTicks(seq=self._seq, stamp_ns=stamp, left=self._count["left_ticks"],
                          right=self._count["right_ticks"], left_speed=speeds[0],
                          right_speed=speeds[1], status=status, estop=estop,
                          errors=self.errors.as_dict(), stamp_uncertainty_ns=uncertainty)

    def poll(self, count: int | None = None, stop: Any | None = None,
             max_silence_s: float | None = None) -> Iterator[WheelTicks]:
        """Read at ``rate_hz`` on absolute deadlines; yields each successful read.

        ``count`` limits the number of messages; ``stop`` (a threading.Event) ends the loop;
        ``max_silence_s``: raise :class:`ModbusBaseError` when no read succeeded for that long.
        """
        def silent(seconds: float) -> ModbusBaseError:
            return ModbusBaseError(f"{self.config.url}: no reply for {seconds:g} s "
                                   f"({self.errors.as_dict()})")

        return paced_reads(self.read, self.config.rate_hz, self.errors, count=count, stop=stop,
                           max_silence_s=max_silence_s, silence_error=silent)

    # -- set-points ---------------------------------------------------------------------
    def set_wheel_speeds(self, left: float, right: float) -> bool:
        """Write wheel-speed set-points (rad/s).  Refused (raises, nothing sent) unless
        ``allow_setpoints`` is on, the map has set-point registers and the speeds are within
        ``max_wheel_speed``; returns False if the write failed on the wire (counted)."""
        cfg, regmap = self.config, self.config.registers
        if not cfg.allow_setpoints:
            raise ModbusBaseError("wheel speed set-points are disabled (allow_setpoints: false)")
        if regmap.left_setpoint is None or regmap.right_setpoint is None:
            raise ModbusBaseError("register map has no set-point registers")
        for v in (left, right):
            if not (math.isfinite(v) and abs(v) <= cfg.max_wheel_speed):
                raise ModbusBaseError(f"wheel speed {v} rad/s beyond +-{cfg.max_wheel_speed}")
        lf, rf = regmap.left_setpoint, regmap.right_setpoint
        if rf.address == lf.address + lf.words:  # one request for both, so they change together
            return self._request("write_registers", lf.address,
                                 lf.encode(left) + rf.encode(right)) is not None
        return (self._request("write_registers", lf.address, lf.encode(left)) is not None
                and self._request("write_registers", rf.address, rf.encode(right)) is not None)
