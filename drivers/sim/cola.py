"""A simulated SICK TiM5xx speaking CoLa A on a loopback TCP socket.

Answers the LMS1xx/TiM start-up (``SetAccessMode``, ``LMPscancfg``, ``LMCstartmeas``,
``STlms``, ``Run``), ``sEN LMDscandata 1/0`` subscriptions and ``sRN LMDscandata`` requests;
streams ``sSN LMDscandata`` telegrams (811 values, −45°…225° in SICK's frame, DIST1 in mm as a
16-bit channel and RSSI1 as an 8-bit channel) ray-cast from the world along its trajectory at
15 Hz (``time_scale`` speeds it up).  Unknown commands get ``sFA``.

Faults on demand: byte errors at ``fault_rate`` in scan telegrams, truncated telegrams, a stall
(no output, input ignored), unplug (listener and connections closed) and replug (listening
again on the same port).  ``sent`` records each streamed scan's DIST1 values and whether the
telegram left intact.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import select
import socket
import struct
import time

import numpy as np

from .twin import ScanTwin, SignalFaults, serve_until_signal
from .world import NoiseModel, World

log = logging.getLogger(__name__)

PASSWORDS = {"03": "F4724744", "02": "B21ACE26", "04": "81BE23AA"}
START_ANGLE = -450000      # 1/10000 degree, SICK frame (0° = 90° right of forward)
STEP = 3333                # 1/10000 degree
COUNT = 811
SCAN_HZ = 15.0
MAX_RANGE_MM = 25000


def _hex(v: int) -> str:
    return format(v & 0xFFFFFFFF, "X")


def _xor(data: bytes) -> int:
    out = 0
    for b in data:
        out ^= b
    return out


def _cola_b(payload: bytes) -> bytes:
    return b"\x02\x02\x02\x02" + len(payload).to_bytes(4, "big") + payload + bytes([_xor(payload)])


# CoLa B argument formats of the replies (keyed by method/variable name; sFA: error code)
_B_REPLY_ARGS = {"SetAccessMode": ">B", "LMCstartmeas": ">B", "LMCstopmeas": ">B", "Run": ">B",
                 "LMDscandata": ">B", "LMPscancfg": ">IHIii", "STlms": ">H", "sFA": ">H"}


class _Client:
    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buf = bytearray()
        self.level = 0
        self.subscribed = False


class ColaTwin(ScanTwin):
    """The simulated TiM5xx; ``start()`` runs it in a thread, ``stop()`` ends it."""

    _thread_name = "cola-twin"

    def __init__(self, world: str | World = "room", *, host: str = "127.0.0.1", port: int = 0,
                 seed: int = 0, fault_rate: float = 0.0, time_scale: float = 1.0,
                 noise: NoiseModel | None = None, binary: bool = False) -> None:
        super().__init__(world, seed=seed, fault_rate=fault_rate, time_scale=time_scale,
                         noise=noise)
        self.binary = binary   # CoLa B instead of CoLa A
        self.host = host
        self.listener: socket.socket | None = None
        self._listen(port)
        self.port = self.listener.getsockname()[1]
        self.clients: list[_Client] = []
        self._power_on()

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def url(self) -> str:
        return f"tcp://{self.address}"

    def _listen(self, port: int) -> None:
        s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((self.host, port))
        s.listen(4)
        s.setblocking(False)
        self.listener = s

    def _power_on(self) -> None:
        self.measuring = False
        self.ready_at = 0.0
        self.t_sim = 0.0
        self.telegram_counter = 0
        self.scan_counter = 0
        self._next_due = time.monotonic()
        self._t0 = time.monotonic()

    # -- faults (truncate, stall, unplug, replug: TwinControl) -------------------------------
    def _unplug(self) -> None:
        """Close the connections and stop listening."""
        for c in self.clients:
            with contextlib.suppress(OSError):
                c.sock.close()
        self.clients = []
        if self.listener is not None:
            self.listener.close()
            self.listener = None
        self.stats["unplugs"] += 1

    def _replug(self) -> None:
        """Listen again on the same port; the device has been power-cycled."""
        if self.listener is None:
            self._listen(self.port)
            self._power_on()
            self.stats["replugs"] += 1

    # -- life cycle (start, __enter__/__exit__: TwinControl) ----------------------------------
    def stop(self) -> None:
        super().stop()
        self._unplug()

    def _run(self) -> None:
        while self._running:
            self._serve_requests()
            if self.listener is None:
                time.sleep(0.01)
                continue
            now = time.monotonic()
            stalled = now < self._stall_until
            wait = 0.02
            if self.measuring and any(c.subscribed for c in self.clients) and not stalled:
                wait = max(0.0, min(wait, self._next_due - now))
            socks = [self.listener] + [c.sock for c in self.clients]
            try:
                ready, _, _ = select.select(socks, [], [], wait)
            except (OSError, ValueError):
                self.clients = [c for c in self.clients if c.sock.fileno() >= 0]
                continue
            try:
                if self.listener in ready:
                    self._accept()
                for c in list(self.clients):
                    if c.sock in ready:
                        self._receive(c, discard=stalled)
                if not stalled and time.monotonic() >= self._next_due:
                    self._stream()
            except Exception:  # keep the device alive whatever a test throws at it
                log.exception("cola twin error")

    def _accept(self) -> None:
        try:
            sock, _ = self.listener.accept()
        except OSError:
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(1.0)
        self.clients.append(_Client(sock))

    def _drop(self, c: _Client) -> None:
        with contextlib.suppress(OSError):
            c.sock.close()
        if c in self.clients:
            self.clients.remove(c)

    def _send(self, c: _Client, data: bytes) -> None:
        try:
            c.sock.sendall(data)
        except OSError:
            self._drop(c)

    def _receive(self, c: _Client, discard: bool) -> None:
        try:
            data = c.sock.recv(65536)
        except OSError:
            data = b""
        if not data:
            self._drop(c)
            return
        if discard:
            return
        c.buf += data
        if self.binary:
            self._receive_b(c)
            return
        while True:
            s = c.buf.find(b"\x02")
            e = c.buf.find(b"\x03", s + 1) if s >= 0 else -1
            if s < 0 or e < 0:
                if s < 0:
                    c.buf.clear()
                return
            text = bytes(c.buf[s + 1:e]).decode("ascii", "replace")
            del c.buf[:e + 1]
            self._command(c, text)

    def _receive_b(self, c: _Client) -> None:
        """CoLa B commands, translated to the CoLa A text the command handler speaks."""
        while True:
            i = c.buf.find(b"\x02\x02\x02\x02")
            if i < 0 or len(c.buf) < i + 8:
                return
            n = int.from_bytes(c.buf[i + 4:i + 8], "big")
            if len(c.buf) < i + 9 + n:
                return
            payload = bytes(c.buf[i + 8:i + 8 + n])
            ok = _xor(payload) == c.buf[i + 8 + n]
            del c.buf[:i + 9 + n]
            if not ok:
                self.stats["bad_checksum"] += 1
                continue
            parts = payload.split(b" ", 2)
            head = b" ".join(parts[:2]).decode("ascii", "replace")
            args = parts[2] if len(parts) > 2 else b""
            if head == "sMN SetAccessMode" and len(args) == 5:
                level, pw = struct.unpack(">BI", args)
                head += f" {level:02d} {pw:08X}"
            elif head == "sEN LMDscandata" and len(args) == 1:
                head += f" {args[0]}"
            self._command(c, head)

    # -- commands ---------------------------------------------------------------------------
    def _reply(self, c: _Client, text: str) -> None:
        if not self.binary:
            self._send(c, b"\x02" + text.encode("ascii") + b"\x03")
            return
        tok = text.split(" ")
        fmt = _B_REPLY_ARGS.get(tok[0] if tok[0] == "sFA" else tok[1], "")
        fields = tok[1:] if tok[0] == "sFA" else tok[2:]
        vals = [int(t, 16) - ((1 << 32) if f == "i" and int(t, 16) >= 1 << 31 else 0)
                for t, f in zip(fields, fmt.lstrip(">"), strict=False)]
        head = tok[0] if tok[0] == "sFA" else " ".join(tok[:2])
        body = struct.pack(fmt, *vals) if fmt else b""
        self._send(c, _cola_b(head.encode("ascii") + (b" " + body if body else b"")))

    def _command(self, c: _Client, text: str) -> None:
        tok = text.split(" ")
        self.stats["commands"] += 1
        kind, name, args = tok[0], tok[1] if len(tok) > 1 else "", tok[2:]
        if kind == "sMN" and name == "SetAccessMode" and len(args) == 2:
            ok = PASSWORDS.get(args[0]) == args[1]
            if ok:
                c.level = int(args[0])
            self._reply(c, f"sAN SetAccessMode {1 if ok else 0}")
        elif kind == "sRN" and name == "LMPscancfg":
            self._reply(c, f"sRA LMPscancfg {_hex(int(SCAN_HZ * 100))} 1 {_hex(STEP)} "
                           f"{_hex(START_ANGLE)} {_hex(START_ANGLE + STEP * (COUNT - 1))}")
        elif kind == "sMN" and name == "LMCstartmeas":
            if not self.measuring:
                self.measuring = True
                self.ready_at = time.monotonic() + 0.1 / self.time_scale
            self._reply(c, "sAN LMCstartmeas 0")
        elif kind == "sMN" and name == "LMCstopmeas":
            self.measuring = False
            self._reply(c, "sAN LMCstopmeas 0")
        elif kind == "sRN" and name == "STlms":
            state = 7 if self.measuring and time.monotonic() >= self.ready_at else 3
            self._reply(c, f"sRA STlms {state} 0 8 00:00:00 8 01.01.2026 0 0 0")
        elif kind == "sMN" and name == "Run":
            self._reply(c, "sAN Run 1")
        elif kind == "sEN" and name == "LMDscandata" and args in (["1"], ["0"]):
            c.subscribed = args == ["1"]
            if c.subscribed:
                self._next_due = time.monotonic()
            self._reply(c, f"sEA LMDscandata {args[0]}")
        elif kind == "sRN" and name == "LMDscandata":
            self._send(c, self._scandata("sRA")[0])
        elif kind == "sRN" and name == "DeviceIdent":
            self._reply(c, "sRA DeviceIdent 10 TiM5xx-SIM 8 V9.99.99")
        else:
            self._reply(c, "sFA 2")   # method/variable unknown

    # -- scans ------------------------------------------------------------------------------
    def _scandata(self, kind: str) -> tuple[bytes, bytes]:
        """One scan telegram (framed, in the twin's protocol) and its DIST1 values as a key."""
        idx = np.arange(COUNT)
        sick_deg = (START_ANGLE + idx * STEP) / 1e4
        angles = np.radians(sick_deg - 90.0)
        self.truth.append((self.scan_counter + 1, self.t_sim, *self.world.trajectory(self.t_sim)))
        r = self.world.scan(self.t_sim, angles, MAX_RANGE_MM / 1000.0, self.noise, self.rng)
        mm = np.where(np.isfinite(r), np.clip(np.rint(r * 1000.0), 1, MAX_RANGE_MM), 0)
        dist = mm.astype(np.int64)
        rssi = np.where(dist > 0, np.clip(255 - dist // 120, 10, 255), 0)
        self.telegram_counter += 1
        self.scan_counter += 1
        t_us = int((time.monotonic() - self._t0) * 1e6) & 0xFFFFFFFF
        self.t_sim += 1.0 / SCAN_HZ
        if self.binary:
            ch = b""
            for name, vals, dtype in ((b"DIST1", dist, ">u2"), (b"RSSI1", rssi, "u1")):
                ch += (b"\x00\x01" + name + struct.pack(">ffiHH", 1.0, 0.0, START_ANGLE, STEP,
                                                          COUNT) + vals.astype(dtype).tobytes())
            head = struct.pack(">HHIBBHHIIBBBBHIIH", 1, 1, 0x1078AAA, 0, 0,
                               self.telegram_counter & 0xFFFF, self.scan_counter & 0xFFFF,
                               t_us, (t_us + 150) & 0xFFFFFFFF, 0, 0, 0, 0, 0,
                               int(SCAN_HZ * 100), 0xA2, 0)
            tail = struct.pack(">HHB", 0, 1, 7) + b"TiM5SIM" + struct.pack(">HHH", 0, 0, 0)
            payload = kind.encode() + b" LMDscandata " + head + ch + tail
            return _cola_b(payload), dist.astype("<u2").tobytes()
        scale = struct.pack(">f", 1.0).hex().upper()
        zero = struct.pack(">f", 0.0).hex().upper()
        head = ["LMDscandata", "1", "1", "1078AAA", "0", "0",
                _hex(self.telegram_counter & 0xFFFF), _hex(self.scan_counter & 0xFFFF),
                _hex(t_us), _hex(t_us + 150), "0", "0", "0", "0", "0",
                _hex(int(SCAN_HZ * 100)), "A2", "0"]
        dist_tok = " ".join(format(v, "X") for v in dist)
        rssi_tok = " ".join(format(v, "X") for v in rssi)
        body = (f"{kind} " + " ".join(head)
                + f" 1 DIST1 {scale} {zero} {_hex(START_ANGLE)} {_hex(STEP)} {_hex(COUNT)} "
                + dist_tok
                + f" 1 RSSI1 {scale} {zero} {_hex(START_ANGLE)} {_hex(STEP)} {_hex(COUNT)} "
                + rssi_tok + " 0 1 7 TiM5SIM 0 0 0")
        return b"\x02" + body.encode("ascii") + b"\x03", dist.astype("<u2").tobytes()

    def _stream(self) -> None:
        subs = [c for c in self.clients if c.subscribed]
        if not (self.measuring and subs):
            return
        period = 1.0 / SCAN_HZ / self.time_scale
        now = time.monotonic()
        self._next_due = max(self._next_due + period, now - 2 * period)
        original, key = self._scandata("sSN")
        data = original
        intact = True
        if self._take_truncate():
            data = data[:int(self.rng.integers(2, len(data) - 1))]
            intact = False
            self.stats["truncated"] += 1
        elif self.fault_rate > 0:
            arr = np.frombuffer(data, np.uint8).copy()
            hit = self.rng.random(len(arr)) < self.fault_rate
            if hit.any():
                arr[hit] = self.rng.integers(0, 256, int(hit.sum()), dtype=np.uint8)
                data = arr.tobytes()
                intact = data == original
                self.stats["corrupted"] += not intact
        self.sent.append((key, intact))
        self.stats["scans"] += 1
        for c in subs:
            self._send(c, data)


def main(args: argparse.Namespace) -> int:
    """``cgamap sim-device cola``: print host:port, serve until SIGINT/SIGTERM.

    ``--port 2112`` serves CoLa B (binary), as the real devices do on that port; any other port
    CoLa A.  SIGUSR1 drops the connection and stops listening for 2 s; SIGUSR2 stalls for 2 s.
    """
    port = getattr(args, "port", 0) or 0
    twin = ColaTwin(getattr(args, "world", "room"), port=port, binary=port == 2112,
                    seed=getattr(args, "seed", 0), fault_rate=getattr(args, "fault_rate", 0.0))
    return serve_until_signal(
        lambda: twin.start().address, twin.stop,
        banner=f"CoLa {'B' if twin.binary else 'A'} twin (TiM5xx) in world "
               f"{twin.world.name!r}; SIGUSR1 = drop 2 s, SIGUSR2 = stall 2 s",
        faults=SignalFaults(twin.unplug, twin.replug, twin.stall))
