"""A simulated SICK LMS2xx: speaks the telegram protocol from the device side on a pty.

Written independently of the driver (its own CRC loop and framing) so that a mistake on one
side is not mirrored on the other.  Behaviour (reference lasers.md §1):

- power-on at 9600 baud, request mode, variant 180°/0.5°, cm units, measuring mode 00;
- every valid telegram is answered by the ACK byte 0x06 and a reply ``command + 0x80`` ending
  with status 0x10; a bad CRC gets the NAK byte 0x15; an unknown command the 0x92 telegram;
- while the host's line rate (read from the pty's termios) differs from the twin's, input is
  discarded and output is garbled, so baud detection works as on a real line;
- the mirror sweeps at 75 Hz of host time (``time_scale`` speeds it and the line up for
  tests), counting sweeps from ``first_sweep``; ``20 24`` streams ``B0`` scans ray-cast from
  the world along its trajectory: whenever the line is free, the latest sweep (or pair of
  sweeps for a 361-value scan) not yet sent, so at low baud sweeps are skipped and the
  real-time index (the sweep count's low byte) jumps; 0.25° (and 0.5° with ``interlace_half``)
  is sent as interlaced partial scans, one sweep each, the partials in turn;
- the line is busy for the wire time of what was written (10 bits a byte at the current
  baud); with ``pace_output`` the bytes also come out at that rate, in ~2 ms chunks (a pty
  would otherwise deliver a whole telegram at once), so a host sees a telegram's last byte
  its wire time after the first, as on a real line;
- fault injection on demand: byte errors at ``fault_rate`` per byte, truncated telegrams,
  stalls, unplug (pty closed, link removed) and replug (a fresh pty behind the same link; the
  device comes back powered up afresh, at 9600 baud).

``sent`` records every streamed scan telegram's value bytes and whether it left intact, so a
test can check that nothing corrupted was delivered; ``measured`` (same order) its last sweep's
count and the host monotonic ns at which that sweep ended, the instant a driver's stamp aims at.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import tempfile
import time

import numpy as np

from .pty_device import PtyClosed, PtyDevice
from .twin import ScanTwin, SignalFaults, serve_until_signal
from .world import NoiseModel, World

log = logging.getLogger(__name__)

_MASK_BITS = {0x00: 13, 0x01: 13, 0x02: 13, 0x03: 14, 0x04: 14, 0x05: 15, 0x06: 15,
              0x0F: 16, 0x3F: 16}
_UNIT = {0: 0.01, 1: 0.001, 2: 0.1}
_BAUDS = {0x40: 38400, 0x41: 19200, 0x42: 9600, 0x48: 500000}
_VARIANTS = {(180, 100), (180, 50), (100, 100), (100, 50), (100, 25)}
STATUS_OK = 0x10
SWEEP_HZ = 75.0
PACE_CHUNK_S = 0.002   # with pace_output: bytes are written in chunks of about this wire time


def sick_crc(data: bytes) -> int:
    """The SICK CRC, byte by byte as the reference pseudo-code gives it (§1.2)."""
    crc = 0
    prev = 0
    for b in data:
        if crc & 0x8000:
            crc = ((crc & 0x7FFF) << 1) ^ 0x8005
        else:
            crc = (crc << 1) & 0xFFFF
        crc ^= b | (prev << 8)
        prev = b
    return crc


def telegram(payload: bytes, address: int = 0x80) -> bytes:
    head = bytes([0x02, address]) + len(payload).to_bytes(2, "little") + payload
    return head + sick_crc(head).to_bytes(2, "little")


class _HostFrames:
    """Host→LMS telegrams (address 0x00); yields payloads or None for a bad CRC."""

    def __init__(self) -> None:
        self.buf = bytearray()

    def feed(self, data: bytes) -> list[bytes | None]:
        self.buf += data
        out: list[bytes | None] = []
        while True:
            i = self.buf.find(b"\x02\x00")
            if i < 0:
                del self.buf[:-1]
                return out
            del self.buf[:i]
            if len(self.buf) < 4:
                return out
            n = int.from_bytes(self.buf[2:4], "little")
            if n == 0 or n > 812:
                del self.buf[:1]
                continue
            if len(self.buf) < n + 6:
                return out
            body = bytes(self.buf[:n + 4])
            if sick_crc(body) == int.from_bytes(self.buf[n + 4:n + 6], "little"):
                out.append(body[4:])
                del self.buf[:n + 6]
            else:
                out.append(None)
                del self.buf[:1]


def default_config() -> bytearray:
    """34 configuration bytes (the ``77`` payload without its command byte)."""
    cfg = bytearray(34)
    cfg[2] = 70    # stop threshold
    cfg[5] = 0x00  # measuring mode: 8/80 m, fields A, B, dazzle
    cfg[6] = 0x00  # units: cm
    return cfg


class Lms2xxTwin(ScanTwin):
    """The simulated LMS on a pty; ``start()`` runs it in a thread, ``stop()`` ends it."""

    _thread_name = "lms2xx-twin"

    def __init__(self, world: str | World = "corridor", *, link: str | None = None,
                 seed: int = 0, fault_rate: float = 0.0, time_scale: float = 1.0,
                 noise: NoiseModel | None = None, interlace_half: bool = False,
                 type_string: str = "LMS291-S05", pace_output: bool = False,
                 first_sweep: int = 0) -> None:
        super().__init__(world, seed=seed, fault_rate=fault_rate, time_scale=time_scale,
                         noise=noise)
        self.interlace_half = interlace_half
        self.type_string = type_string
        self.pace_output = pace_output
        self.first_sweep = int(first_sweep)
        # per streamed scan telegram (as ``sent``): (sweep count, host ns the sweep ended)
        self.measured: collections.deque[tuple[int, int]] = collections.deque(
            maxlen=self.sent.maxlen)
        self._outq: collections.deque[tuple[float, bytes]] = collections.deque()  # paced
        self._own_dir = None
        if link is None:
            self._own_dir = tempfile.mkdtemp(prefix="cgamap-lms2xx-")
            link = os.path.join(self._own_dir, "ttyLMS")
        self.pty = PtyDevice(link)
        self._power_on()

    @property
    def path(self) -> str:
        return self.pty.path

    # -- state ----------------------------------------------------------------------------
    def _power_on(self) -> None:
        self.baud = 9600
        self.mode = 0x25           # request mode
        self.installation = False
        self.angle, self.res = 180, 50
        self.config = default_config()
        self.t_sim = 0.0
        self.partial = 0
        self._mirror_t0 = time.monotonic()   # sweep first_sweep + i ends at t0 + (i + 1) P
        self.sweep = self._latest_sweep()    # the last sweep sent (or skipped)
        self._line_free = 0.0                # when the line is done with what was written
        self._frames = _HostFrames()

    @property
    def rt_counter(self) -> int:
        """The last sent sweep's count (its low byte is the real-time index)."""
        return self.sweep

    @property
    def streaming(self) -> bool:
        return self.mode == 0x24

    # -- fault injection (truncate, stall, unplug, replug: TwinControl) ----------------------
    def _unplug(self) -> None:
        """Close the pty and remove the link, as pulling the cable/adapter looks to the host."""
        self.pty.disconnect()
        self.stats["unplugs"] += 1

    def _replug(self) -> None:
        """A fresh pty behind the same link; the device has been power-cycled (9600 baud)."""
        self.pty.reconnect()
        self._outq.clear()
        self._power_on()
        self.stats["replugs"] += 1

    # -- life cycle (start, __enter__/__exit__: TwinControl) ---------------------------------
    def stop(self) -> None:
        super().stop()
        self.pty.close()
        if self._own_dir:
            try:
                os.rmdir(self._own_dir)
            except OSError:
                pass

    def _run(self) -> None:
        while self._running:
            self._serve_requests()
            if not self.pty.is_open:
                time.sleep(0.01)
                continue
            now = time.monotonic()
            if now < self._stall_until:
                time.sleep(min(0.01, self._stall_until - now))
                if time.monotonic() >= self._stall_until:
                    self.pty.flush_input()
                continue
            wait = 0.02
            if self.streaming:
                wait = min(wait, self._stream_due() - now)
            if self._outq:
                wait = min(wait, self._outq[0][0] - now)
            try:
                data = self.pty.read(4096, max(0.0, wait))
                if data:
                    self._on_input(data)
                self._drain()
                if self.streaming and time.monotonic() >= self._stream_due():
                    self._stream_one()
                    self._drain()
            except PtyClosed:
                time.sleep(0.01)
            except Exception:  # keep the device alive whatever a test throws at it
                log.exception("lms2xx twin error")

    # -- output -----------------------------------------------------------------------------
    def _baud_matches(self) -> bool:
        host = self.pty.host_baud()
        return host is None or host == self.baud

    def _emit(self, data: bytes, corruptible: bool = True) -> bool:
        """Write bytes (garbled on a baud mismatch, with injected errors); True if intact."""
        intact = True
        if not self._baud_matches():
            data = self.rng.integers(0, 256, max(1, len(data) // 4), dtype=np.uint8).tobytes()
            intact = False
        elif corruptible and self.fault_rate > 0:
            arr = np.frombuffer(data, np.uint8).copy()
            hit = self.rng.random(len(arr)) < self.fault_rate
            if hit.any():
                arr[hit] ^= self.rng.integers(1, 256, int(hit.sum()), dtype=np.uint8)
                data = arr.tobytes()
                intact = False
                self.stats["corrupted"] += 1
        now = time.monotonic()
        start = max(now, self._line_free)
        byte_s = 10.0 / self.baud / self.time_scale
        self._line_free = start + len(data) * byte_s
        if not self.pace_output:
            self.pty.write(data)
            return intact
        # each chunk leaves once its last byte would have been received
        step = max(1, int(PACE_CHUNK_S / byte_s))
        for i in range(0, len(data), step):
            chunk = data[i:i + step]
            self._outq.append((start + (i + len(chunk)) * byte_s, chunk))
        self._drain()
        return intact

    def _drain(self) -> None:
        """Write the paced chunks that are due."""
        now = time.monotonic()
        while self._outq and self._outq[0][0] <= now:
            self.pty.write(self._outq.popleft()[1])

    def _reply(self, payload: bytes) -> None:
        self._emit(bytes([0x06]) + telegram(payload + bytes([STATUS_OK])))

    # -- input -------------------------------------------------------------------------------
    def _on_input(self, data: bytes) -> None:
        if not self._baud_matches():
            self.stats["baud_mismatch_bytes"] += len(data)
            self._frames.buf.clear()
            return
        for payload in self._frames.feed(data):
            if payload is None:
                self.stats["bad_crc"] += 1
                self._emit(bytes([0x15]))
            else:
                self.stats["commands"] += 1
                self._command(payload)

    def _command(self, p: bytes) -> None:
        cmd = p[0]
        if cmd == 0x20 and len(p) >= 2:
            self._mode_switch(p)
        elif cmd == 0x30 and len(p) >= 2:
            self._emit(bytes([0x06]))
            self._emit(telegram(self._scan_payload(self._latest_sweep(), full=True)))
        elif cmd == 0x31:
            self._reply(self._status_payload())
        elif cmd == 0x32:
            self._reply(b"\xB2" + bytes(8))
        elif cmd == 0x3A:
            self._reply(b"\xBA" + self.type_string.encode("ascii"))
        elif cmd == 0x3B and len(p) >= 5:
            angle = int.from_bytes(p[1:3], "little")
            res = int.from_bytes(p[3:5], "little")
            ok = (angle, res) in _VARIANTS and not self.streaming
            if ok:
                self.angle, self.res = angle, res
                self.partial = 0
            self._reply(bytes([0xBB, 1 if ok else 0]) + self.angle.to_bytes(2, "little")
                        + self.res.to_bytes(2, "little"))
        elif cmd == 0x74:
            self._reply(b"\xF4" + bytes(self.config))
        elif cmd == 0x77 and len(p) >= 33:
            ok = self.installation and len(p) - 1 in (32, 34)
            if ok:
                self.config[:len(p) - 1] = p[1:]
            self._reply(bytes([0xF7, 1 if ok else 0]) + bytes(self.config))
        elif cmd == 0x10:
            self._reply(b"\x91")
            self._power_on()
            time.sleep(0.3 / self.time_scale)
            self._emit(telegram(b"\x90" + b"LMS ready" + bytes([STATUS_OK])))
        else:
            self._emit(bytes([0x06]) + telegram(bytes([0x92, cmd, STATUS_OK])))

    def _mode_switch(self, p: bytes) -> None:
        mode = p[1]
        if mode in _BAUDS:
            self._reply(b"\xA0\x00")
            time.sleep(0.002)
            self.baud = _BAUDS[mode]
            return
        ok = True
        if mode == 0x00:
            ok = p[2:10] == b"SICK_LMS"
            self.installation = ok
        elif mode in (0x24, 0x25):
            self.installation = False
            if mode == 0x24 and not self.streaming:
                self.sweep = max(self.sweep, self._latest_sweep())  # stream from the next
                self.partial = 0
        else:
            ok = False
        if ok:
            self.mode = mode
        self._reply(bytes([0xA0, 0 if ok else 1]))

    def _status_payload(self) -> bytes:
        d = bytearray(152)
        d[0] = 0xB1
        d[1:8] = b"V02.10 "
        d[8] = self.mode
        d[9] = 0
        d[102] = self.config[5]
        d[107:109] = self.angle.to_bytes(2, "little")
        d[109:111] = self.res.to_bytes(2, "little")
        d[120] = 0
        return bytes(d)

    # -- scans -------------------------------------------------------------------------------
    def _interlace(self) -> int:
        k = 100 // self.res
        if k == 1 or (k == 2 and not self.interlace_half):
            return 1
        return k

    def _sweeps_per_telegram(self) -> int:
        """1, or the sweeps a non-interlaced finer-than-1° scan is measured in (0.5°: two)."""
        return 1 if self._interlace() > 1 else 100 // self.res

    def _sweep_s(self) -> float:
        return 1.0 / (SWEEP_HZ * self.time_scale)

    def _sweep_end(self, j: int) -> float:
        """Host monotonic s at which sweep ``j`` ended."""
        return self._mirror_t0 + (j - self.first_sweep + 1) * self._sweep_s()

    def _latest_sweep(self, now: float | None = None) -> int:
        """The last sweep that has ended (first_sweep - 1 before the first one)."""
        now = time.monotonic() if now is None else now
        return self.first_sweep - 1 + int((now - self._mirror_t0) // self._sweep_s())

    def _slot(self) -> tuple[int, int]:
        """Which sweeps end a telegram: those j with j % m == r (the next partial's sweeps
        when interlaced, the last of each group of sweeps otherwise)."""
        k = self._interlace()
        if k > 1:
            return k, self.partial
        s = self._sweeps_per_telegram()
        return s, s - 1

    def _stream_due(self) -> float:
        """When the next scan telegram can go: its sweep has ended and the line is free."""
        m, r = self._slot()
        j = self.sweep + 1
        j += (r - j) % m
        return max(self._line_free, self._sweep_end(j))

    def _scan_payload(self, j: int, full: bool = False) -> bytes:
        """The ``B0`` payload of the scan that sweep ``j`` ended."""
        k = 1 if full else self._interlace()
        n_full = self.angle * 100 // self.res + 1
        p = self.partial if k > 1 else 0
        idx = np.arange(p, n_full, k)
        res_rad = np.radians(self.res / 100.0)
        angles = -np.radians(self.angle / 2.0) + idx * res_rad
        bits = _MASK_BITS.get(self.config[5], 13)
        mask = (1 << bits) - 1
        unit_code = self.config[6] if self.config[6] in _UNIT else 0
        unit = _UNIT[unit_code]
        # the simulated clock: sweep first_sweep ends at 1/75 s
        self.t_sim = (j - self.first_sweep + 1) / SWEEP_HZ
        self.truth.append((j, self.t_sim, *self.world.trajectory(self.t_sim)))
        r = self.world.scan(self.t_sim, angles, mask * unit, self.noise, self.rng)
        with np.errstate(invalid="ignore"):
            counts = np.where(np.isfinite(r), np.rint(r / unit), mask)
        counts = np.clip(counts, 0, mask).astype(np.uint16)
        counts[counts >= mask - 8] = mask
        w = len(idx) | (p << 11) | (unit_code << 14)
        out = bytearray(b"\xB0") + w.to_bytes(2, "little") + counts.astype("<u2").tobytes()
        if self.config[4] & 0x02:  # availability flag: send real-time indices
            out.append(j & 0xFF)
        out.append(STATUS_OK)
        return bytes(out)

    def _stream_one(self) -> None:
        """Send the latest ended sweep of the next telegram's slot (skipping older ones)."""
        m, r = self._slot()
        latest = self._latest_sweep()
        j = latest - (latest - r) % m
        if j <= self.sweep:
            return
        payload = self._scan_payload(j)
        self.sweep = j
        if self._interlace() > 1:
            self.partial = (self.partial + 1) % self._interlace()
        n = int.from_bytes(payload[1:3], "little") & 0x3FF
        data = telegram(payload)
        self.measured.append((j, int(self._sweep_end(j) * 1e9)))
        if self._take_truncate():
            data = data[:int(self.rng.integers(4, len(data) - 1))]
            self.stats["truncated"] += 1
            self._emit(data)
            self.sent.append((payload[3:3 + 2 * n], False))
            return
        intact = self._emit(data)
        self.sent.append((payload[3:3 + 2 * n], intact))
        self.stats["scans"] += 1


def main(args: argparse.Namespace) -> int:
    """``cgamap sim-device lms2xx``: print the device path, serve until SIGINT/SIGTERM.

    ``--pace-output`` sets ``pace_output`` (bytes at the wire rate, see the module docstring).
    SIGUSR1 unplugs the device for 2 s and plugs it back; SIGUSR2 stalls it for 2 s.
    """
    twin = Lms2xxTwin(getattr(args, "world", "corridor"), seed=getattr(args, "seed", 0),
                      fault_rate=getattr(args, "fault_rate", 0.0),
                      pace_output=bool(getattr(args, "pace_output", False)))
    return serve_until_signal(
        lambda: twin.start().path, twin.stop,
        banner=f"lms2xx twin in world {twin.world.name!r}; SIGUSR1 = unplug 2 s, "
               "SIGUSR2 = stall 2 s",
        faults=SignalFaults(twin.unplug, twin.replug, twin.stall))
