"""Hokuyo SCIP 2.0 laser driver (URG-04LX, UTM-30LX, UST-xxLX) over any transport.

The byte-level work (checksums, decoding, reply framing) is :class:`~.scip.ScipParser`; this
module does the conversation and turns decoded scans into :class:`LaserScan` messages.

Start-up (reference ``lasers.md`` section 3.2): ``QT`` probe (a SCIP 1.1 device answers ``E``:
switch with ``SCIP2.0``; a ``0E`` answer can mean time-adjust mode: leave it with ``TM2``) →
``VV``, ``PP``, ``II`` into a :class:`SensorInfo` → ``BM`` (00 or 02) → ``MD``/``MS``/``ME``
endless streaming, or nothing in ``mode="single"`` (each read sends ``GD``/``GS``/``GE``).
Stop: ``QT``.  Loss of the port or a stall is handled by :class:`LaserDriver` (reconnect).

Ranges: a value below DMIN (the sensor's error codes) or above DMAX is no return: NaN.
``device_stamp`` is the unwrapped SCIP millisecond timestamp; :meth:`HokuyoDriver.sync_time`
(``TM0/TM1/TM2``) estimates the offset from it to ``time.monotonic_ns()``.  A scan's
``stamp_ns`` is the arrival time it would have had on an idle host: its SCIP timestamp through
a :class:`~.device_clock.DeviceClock`, so a scan read late on a busy host keeps its instant.
"""

from __future__ import annotations

import logging
import time
from collections import deque

import numpy as np

from .device_clock import DeviceClock
from .laser import DeviceError, LaserDriver
from .messages import LaserScan
from .scip import (
    CHARS_PER_VALUE,
    ScipParser,
    ScipReply,
    ScipScan,
    SensorInfo,
    decode,
    parse_fields,
    status_text,
)
from .transport import Transport, TransportError

log = logging.getLogger(__name__)

ENCODINGS = ("D", "S", "E")   # 3-char ranges, 2-char ranges, ranges + intensities
# RS-232 rates SCIP's SS command takes (urg_library's list); power-on default 19200
BAUD_RATES = (19200, 57600, 115200, 250000, 500000, 750000)


class ScipError(DeviceError):
    """A SCIP command was answered with an error status, or not answered at all."""

    def __init__(self, command: str, status: str, detail: str = "") -> None:
        self.command, self.status = command, status
        super().__init__(f"hokuyo: {command!r} answered {status!r}: "
                         f"{detail or status_text(status)}")


def scan_to_message(scan: ScipScan, info: SensorInfo, stamp_ns: int | None = None) -> LaserScan:
    """A decoded SCIP scan as a :class:`LaserScan` (ranges in m, no return as NaN).

    A cluster of steps is placed at its centre step.
    """
    mm = scan.ranges_mm
    ranges = mm.astype(np.float64) * 1e-3
    ranges[(mm < info.dmin) | (mm > info.dmax)] = np.nan
    intens = scan.intensity.astype(np.float64) if scan.intensity is not None else None
    return LaserScan(
        seq=0,
        stamp_ns=int(stamp_ns if stamp_ns is not None else
                     (scan.stamp_ns if scan.stamp_ns is not None else time.monotonic_ns())),
        angle_min=info.angle_of(scan.start + (scan.cluster - 1) / 2.0),
        angle_increment=scan.cluster * info.step_angle,
        ranges=ranges,
        range_min=info.dmin * 1e-3,
        range_max=info.dmax * 1e-3,
        scan_time=info.scan_time,
        intensities=intens,
        device_stamp=scan.device_ms,
    )


class HokuyoDriver(LaserDriver):
    """SCIP 2.0 driver.  ``mode``: "continuous" (MD/MS/ME) or "single" (GD/GS/GE per read).

    ``encoding``: "D" (3-char, any range), "S" (2-char, <= 4095 mm), "E" (with intensities).
    ``start``/``end`` steps default to AMIN/AMAX; ``cluster`` merges that many steps;
    ``skip`` (0-9) skips scans between the ones sent in continuous mode.
    ``baud``: on an RS-232 line, switch the session to this rate with ``SS`` (after finding
    the sensor's current rate among :data:`BAUD_RATES` if the URL's rate gets no answer).
    """

    model = "hokuyo"
    default_baud = 19200        # RS-232 default of the URG-04LX; USB models ignore the rate

    def __init__(self, device: str | Transport, timeout: float = 0.5, *,
                 mode: str = "continuous", encoding: str = "D", start: int | None = None,
                 end: int | None = None, cluster: int = 1, skip: int = 0,
                 command_timeout: float = 0.4, baud: int | None = None, **kw) -> None:
        super().__init__(device, timeout, **kw)
        if mode not in ("continuous", "single"):
            raise ValueError(f"hokuyo: mode must be 'continuous' or 'single', not {mode!r}")
        if encoding not in ENCODINGS:
            raise ValueError(f"hokuyo: encoding must be one of {ENCODINGS}, not {encoding!r}")
        if not 1 <= cluster <= 99 or not 0 <= skip <= 9:
            raise ValueError("hokuyo: cluster must be 1..99 and skip 0..9")
        if baud is not None and baud not in BAUD_RATES:
            raise ValueError(f"hokuyo: baud must be one of {BAUD_RATES}, not {baud}")
        self.baud = baud
        self.mode, self.encoding = mode, encoding
        self.start, self.end, self.cluster, self.skip = start, end, cluster, skip
        self.command_timeout = command_timeout
        self.parser = ScipParser()
        self.parser.errors = self.errors          # one set of counters for the driver
        self.info: SensorInfo | None = None
        self.time_offset_ns: int | None = None    # host monotonic ns minus device ms * 1e6
        self.clock = DeviceClock()                 # scan stamps from the SCIP timestamps
        self._pending: deque[ScipScan] = deque()
        self._scan_cmd = ""
        self._streaming = False

    # -- LaserDriver hooks ---------------------------------------------------------------
    def _start(self) -> None:
        tr = self._tr()
        tr.reset_input()
        self.parser.reset()
        self._pending.clear()
        self._streaming = False
        self._connect_line()
        fields: dict[str, str] = {}
        for cmd in ("VV", "PP", "II"):
            reply = self._command(cmd)
            if reply.status != "00":
                if cmd == "II":          # optional on old firmware
                    continue
                raise ScipError(cmd, reply.status)
            fields.update(parse_fields(reply.lines))
        try:
            self.info = SensorInfo.from_fields(fields)
        except ValueError as exc:
            raise DeviceError(str(exc)) from exc
        self._scan_cmd = self._scan_command()
        self._laser_on()
        if self.mode == "continuous":
            self._start_stream()

    def _receive_scan(self, timeout: float) -> LaserScan | None:
        if self.mode == "single":
            return self.grab(timeout)
        deadline = time.monotonic() + timeout
        while True:
            while self._pending:
                scan = self._pending.popleft()
                if scan.echo != self._scan_cmd:   # an echo digit hit by a byte error
                    self.errors.framing += 1
                    continue
                return scan_to_message(scan, self._info(), self._taken_ns(scan))
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            self._pump(left)

    def _stop(self) -> None:
        self._streaming = False
        try:
            self._command("QT", tries=2)
        except DeviceError:
            pass

    # -- public commands ---------------------------------------------------------------------
    def grab(self, timeout: float | None = None) -> LaserScan | None:
        """One scan with ``G?`` (works whether or not the driver streams)."""
        cmd = self._scan_cmd.replace("M", "G", 1)[:12] if self._scan_cmd else ""
        if not cmd:
            raise DeviceError("hokuyo: not opened")
        self._send(cmd)
        deadline = time.monotonic() + (self.command_timeout if timeout is None else timeout)
        while time.monotonic() < deadline:
            for item in self._pump(deadline - time.monotonic()):
                if isinstance(item, ScipReply) and item.echo == cmd:
                    self.errors.device += 1
                    raise ScipError(cmd, item.status)
            for i, scan in enumerate(self._pending):
                if scan.echo == cmd:
                    del self._pending[i]
                    return scan_to_message(scan, self._info(), self._taken_ns(scan))
        return None

    def _taken_ns(self, scan: ScipScan) -> int | None:
        """``scan``'s host stamp by its device clock (None: the arrival stamp as it is)."""
        if scan.stamp_ns is None:
            return None
        return self.clock.stamp(scan.device_ms, scan.stamp_ns)

    def stop(self) -> None:
        """Stop streaming and switch the laser off (``QT``)."""
        self._stop()

    def resume(self) -> None:
        """Laser on and streaming again after :meth:`stop`."""
        self._laser_on()
        if self.mode == "continuous":
            self._start_stream()

    def reset(self) -> None:
        """``RS``: the sensor stops and resets its settings; then start again."""
        self._streaming = False
        reply = self._command("RS")
        if reply.status not in ("00", "01"):
            raise ScipError("RS", reply.status)
        self.resume()

    def sync_time(self, samples: int = 5) -> int:
        """Estimate ``time_offset_ns`` with ``TM0``/``TM1``×n/``TM2`` (least round-trip sample).

        Streaming is paused for it and restarted.  Returns the offset in ns.
        """
        was_streaming = self._streaming
        if was_streaming:
            self._stop()
        best: tuple[int, int] | None = None
        reply = self._command("TM0")
        if reply.status not in ("00", "02"):
            raise ScipError("TM0", reply.status)
        try:
            for _ in range(max(1, samples)):
                t0 = time.monotonic_ns()
                reply = self._command("TM1")
                t1 = time.monotonic_ns()
                if reply.status != "00" or not reply.lines or len(reply.lines[0]) != 4:
                    raise ScipError("TM1", reply.status, "no time in the reply")
                device_ms = self.parser.unwrap(decode(reply.lines[0]))
                offset = (t0 + t1) // 2 - device_ms * 1_000_000
                if best is None or t1 - t0 < best[0]:
                    best = (t1 - t0, offset)
        finally:
            self._command("TM2")
        assert best is not None
        self.time_offset_ns = best[1]
        if was_streaming:
            self.resume()
        return best[1]

    def device_to_host_ns(self, device_ms: int) -> int | None:
        """Host monotonic ns of a device timestamp, once :meth:`sync_time` has run."""
        if self.time_offset_ns is None:
            return None
        return device_ms * 1_000_000 + self.time_offset_ns

    # -- internals ---------------------------------------------------------------------------
    def _tr(self) -> Transport:
        if self.transport is None:
            raise TransportError(f"{self.url}: not open")
        return self.transport

    def _info(self) -> SensorInfo:
        if self.info is None:
            raise DeviceError("hokuyo: no sensor description (PP) yet")
        return self.info

    def _scan_command(self) -> str:
        info = self._info()
        start = info.amin if self.start is None else self.start
        end = info.amax if self.end is None else self.end
        if not info.amin <= start <= end <= info.amax:
            raise DeviceError(f"hokuyo: steps {start}..{end} outside {info.amin}..{info.amax}")
        return f"M{self.encoding}{start:04d}{end:04d}{self.cluster:02d}{self.skip:d}00"

    def _send(self, cmd: str) -> None:
        self._tr().write(cmd.encode("ascii") + b"\n")

    def _pump(self, timeout: float) -> list[ScipReply | ScipScan]:
        """Read once (up to ``timeout``), parse, queue scans; return everything parsed."""
        data = self._tr().read(65536, max(0.0, timeout))
        if not data:
            return []
        items = self.parser.feed(data, time.monotonic_ns())
        for item in items:
            if isinstance(item, ScipScan):
                self._pending.append(item)
                if len(self._pending) > 64:      # nobody is reading: keep the newest
                    self._pending.popleft()
                    self.errors.dropped += 1
            elif item.echo == self._scan_cmd and item.status not in ("00", "99"):
                # e.g. 0M (unstable) interleaved with the stream
                self.errors.device += 1
                log.warning("%s: %s", self.url, ScipError(item.echo, item.status))
        return items

    def _command(self, cmd: str, timeout: float | None = None, tries: int = 3) -> ScipReply:
        """Send ``cmd`` and wait for the reply with the same echo (scans keep queueing).

        A reply lost to a byte error is dropped by the parser, so the command is sent again
        (every command used here is safe to repeat) up to ``tries`` times.
        """
        wait = self.command_timeout if timeout is None else timeout
        for _ in range(max(1, tries)):
            self._send(cmd)
            deadline = time.monotonic() + wait
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    self.errors.timeout += 1
                    break
                for item in self._pump(left):
                    if isinstance(item, ScipReply) and item.echo == cmd:
                        return item
        raise DeviceError(f"hokuyo: no reply to {cmd!r} within {wait:g} s ({tries} tries)")

    def _connect_line(self) -> None:
        """Probe; on a serial line find the sensor's rate if needed, then switch to ``baud``."""
        tr = self._tr()
        current = tr.baud
        try:
            self._probe()
        except DeviceError:
            if current is None:
                raise
            self._detect_baud(current)
        current = tr.baud
        if current is not None and self.baud is not None and current != self.baud:
            reply = self._command(f"SS{self.baud:06d}")
            if reply.status not in ("00", "03", "04"):   # 03/04: already at that rate
                raise ScipError(f"SS{self.baud:06d}", reply.status)
            tr.set_baud(self.baud)
            log.info("%s: switched from %d to %d baud", self.url, current, self.baud)
            self._probe()

    def _detect_baud(self, tried: int) -> None:
        tr = self._tr()
        for rate in (r for r in BAUD_RATES if r != tried):
            tr.set_baud(rate)
            tr.reset_input()
            self.parser.reset()
            try:
                self._command("QT", tries=1)
            except DeviceError:
                continue
            log.info("%s: sensor answers at %d baud", self.url, rate)
            self._probe()
            return
        raise DeviceError(f"hokuyo: no SCIP answer at any of {BAUD_RATES} baud")

    def _probe(self) -> None:
        """``QT`` until a SCIP 2.0 answer, switching from SCIP 1.1 / TM mode on the way."""
        last: Exception | None = None
        for _ in range(3):
            try:
                reply = self._command("QT", tries=1)
            except DeviceError as exc:
                last = exc
                continue
            if reply.legacy:                     # SCIP 1.1 answers "E"
                log.info("%s: SCIP 1.1 device, switching to SCIP 2.0", self.url)
                self._command("SCIP2.0")
                continue
            if reply.status == "0E":             # maybe time-adjust mode
                self._command("TM2")
                continue
            if reply.status == "00":
                return
            last = ScipError("QT", reply.status)
        raise last or DeviceError("hokuyo: no SCIP 2.0 answer to QT")

    def _laser_on(self) -> None:
        reply = self._command("BM")
        if reply.status not in ("00", "02"):
            self.errors.device += 1
            raise ScipError("BM", reply.status)

    def _start_stream(self) -> None:
        reply = self._command(self._scan_cmd)
        if reply.status != "00":
            self.errors.device += 1
            raise ScipError(self._scan_cmd, reply.status)
        self._streaming = True


__all__ = ["BAUD_RATES", "CHARS_PER_VALUE", "HokuyoDriver", "ScipError", "scan_to_message"]
