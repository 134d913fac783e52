"""Simulated Hokuyo laser speaking SCIP 2.0 from the device side, on a pseudo-terminal
(serial/USB models) or a loopback TCP port (Ethernet models, ``tcp_port=``).

Written apart from the driver (its own encoder, checksum and command handling) so that the
driver's tests exercise two independent readings of the protocol.  It ray-casts a simulated
world along its trajectory (range noise, dropouts) and can inject faults on demand:

- ``fault_rate``: each byte sent is replaced by a different random byte with that probability;
- :meth:`HokuyoTwin.truncate` : the next n scan replies are cut short at a random point;
- :meth:`HokuyoTwin.stall`    : send and answer nothing for a while;
- :meth:`HokuyoTwin.unstable` : the next n scans come as ``0M`` (unstable) error blocks;
- :meth:`HokuyoTwin.disconnect` / :meth:`HokuyoTwin.reconnect`: the pty vanishes and returns
  behind the same path, or the TCP port closes and listens again (an unplug: the sensor
  restarts with the laser off).

Every scan reply sent is recorded in :attr:`HokuyoTwin.sent` (device timestamp, whether it
went out intact, the values encoded) so tests can check what the driver delivered.

Time: the device clock runs ``speed`` times faster than the host's, so tests can stream many
scans quickly with realistic, distinct timestamps (25 ms apart for a UTM-30LX).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
import tempfile
import time
from collections import deque
from dataclasses import dataclass

import numpy as np

from .pty_device import PtyClosed, PtyDevice
from .tcp_device import TcpDevice
from .twin import ScanTwin, SignalFaults, serve_until_signal
from .world import NoiseModel, World

MODELS = {
    "UTM-30LX": dict(dmin=23, dmax=60000, ares=1440, amin=0, amax=1080, afrt=540, scan=2400,
                     prod="SOKUIKI Sensor TOP-URG UTM-30LX", firm="1.20.00(16/Nov./2009)"),
    "URG-04LX": dict(dmin=20, dmax=5600, ares=1024, amin=44, amax=725, afrt=384, scan=600,
                     prod="SOKUIKI Sensor URG-04LX", firm="3.3.00,06/12/20(1,40-1010mm)"),
}
MODELS["UST-10LX"] = dict(MODELS["UTM-30LX"], dmin=20, dmax=30000,
                         prod="SOKUIKI Sensor UST-10LX", firm="1.0.0")
ALIASES = {"utm": "UTM-30LX", "utm-30lx": "UTM-30LX", "urg": "URG-04LX", "urg-04lx": "URG-04LX",
           "ust": "UST-10LX", "ust-10lx": "UST-10LX"}

_SCAN_CMD = re.compile(r"^([GM])([DSE])(\d{4})(\d{4})(\d{2})(?:(\d)(\d{2}))?(;.{0,16})?$")
_WIDTH = {"D": 3, "S": 2, "E": 3}


def sum_char(data: bytes) -> bytes:
    """The device-side checksum character of ``data``."""
    return bytes([(sum(data) & 0x3F) + 0x30])


def encode_values(values: np.ndarray, width: int) -> bytes:
    """Each value as ``width`` characters of 6 bits (+0x30), most significant first."""
    v = np.asarray(values, dtype=np.uint32)[:, None]
    shifts = np.arange(width - 1, -1, -1, dtype=np.uint32) * 6
    return (((v >> shifts) & 0x3F) + 0x30).astype(np.uint8).tobytes()


def data_lines(payload: bytes) -> bytes:
    """Split into lines of at most 64 characters, each followed by its checksum and LF."""
    arr = np.frombuffer(payload, dtype=np.uint8)
    n = len(arr)
    if n == 0:
        return b""
    starts = np.arange(0, n, 64)
    sums = (np.add.reduceat(arr.astype(np.uint32), starts) & 0x3F) + 0x30
    out = bytearray()
    for i, s in enumerate(starts):   # ~51 lines per scan: cheap
        out += arr[s:s + 64].tobytes()
        out.append(int(sums[i]))
        out.append(0x0A)
    return bytes(out)


def info_line(key: str, value: str) -> bytes:
    body = f"{key}:{value}".encode("ascii")
    return body + b";" + sum_char(body) + b"\n"


def scan_reply(echo: str, status: str, timestamp: int, values: np.ndarray, enc: str,
               intensity: np.ndarray | None = None) -> bytes:
    """The bytes of one scan reply: echo, status, timestamp, data lines, blank line."""
    if enc == "E":
        both = np.stack([values, intensity if intensity is not None else values * 0], axis=1)
        payload = encode_values(both.reshape(-1), 3)
    else:
        payload = encode_values(values, _WIDTH[enc])
    tsc = encode_values(np.array([timestamp]), 4)
    st = status.encode("ascii")
    head = echo.encode("ascii", "replace")     # a non-ASCII command echoes as '?'
    return (head + b"\n" + st + sum_char(st) + b"\n" + tsc + sum_char(tsc)
            + b"\n" + data_lines(payload) + b"\n")


@dataclass
class SentScan:
    """What the twin sent for one scan reply (for tests)."""

    timestamp: int          # 24-bit device ms in the reply
    intact: bool            # no byte of the reply corrupted or cut
    values: np.ndarray      # ranges as encoded (mm, device error codes included)
    echo: str
    # corrupted, yet every line still passes its checksum and the character set: no SCIP
    # receiver can tell (the 6-bit checksum misses some multi-byte errors)
    undetectable: bool = False


def _passes_checks(orig: bytes, got: bytes) -> bool:
    """Whether a corrupted scan reply still looks valid line by line (same length)."""
    if len(orig) != len(got) or orig.count(b"\n") != got.count(b"\n"):
        return False
    o_lines, g_lines = orig.split(b"\n"), got.split(b"\n")
    if [len(x) for x in o_lines] != [len(x) for x in g_lines] or o_lines[0] != g_lines[0]:
        return False
    for line in g_lines[1:]:
        if line and (len(line) < 2 or sum_char(line[:-1])[0] != line[-1]):
            return False
    body = b"".join(x[:-1] for x in g_lines[2:] if x)
    return not body.translate(None, bytes(range(0x30, 0x70)))


class HokuyoTwin(ScanTwin):
    """A SCIP 2.0 Hokuyo on a pty.  Use as a context manager or call start()/close().

    ``speed`` is the device clock's rate relative to the host's (ScanTwin's ``time_scale``).
    """

    _thread_name = "hokuyo-twin"
    _join_s = 2.0

    def __init__(self, model: str = "UTM-30LX", world: str | World = "corridor", *,
                 fault_rate: float = 0.0, seed: int = 0, link: str | None = None,
                 speed: float = 1.0, noise: NoiseModel | None = None,
                 scip1: bool = False, clock0_ms: int = 0, status: str = "00",
                 epoch: float | None = None, tcp_port: int | None = None,
                 baud: int | None = None) -> None:
        name = ALIASES.get(model.lower(), model)
        if name not in MODELS:
            raise ValueError(f"unknown Hokuyo model {model!r}; choose from {sorted(MODELS)}")
        if noise is None:
            noise = NoiseModel(sigma=0.01, dropout=0.01)    # more dropouts than ScanTwin's
        super().__init__(world, seed=seed, fault_rate=fault_rate, time_scale=speed, noise=noise)
        self.model = name
        self.p = MODELS[name]
        self.fault_rng = np.random.default_rng(seed + 1)   # byte faults apart from range noise
        self.clock0_ms = int(clock0_ms)
        self.bm_status = status               # answer to BM (e.g. "01" = laser malfunction)
        self.sent: deque[SentScan]            # ScanTwin's record: a SentScan per scan reply
        self.commands: list[str] = []          # every command line received
        self.command_errors = 0                # commands whose handling raised (twin kept serving)
        # a pty (serial and USB models), or loopback TCP (Ethernet models) with tcp_port
        self.dev: PtyDevice | TcpDevice = PtyDevice(link) if tcp_port is None else \
            TcpDevice(port=tcp_port)
        self._scip2 = not scip1
        # host monotonic time (s) at which the device clock reads clock0_ms
        self._t0 = time.monotonic() if epoch is None else float(epoch)
        self._unstable = 0
        # RS-232 emulation (pty only): the rate the sensor talks at; while the host's port is
        # set to another, input is lost and output arrives as garbage.  None: USB (any rate).
        self.power_on_baud = baud
        self._inbuf = b""
        self._power_on()

    # -- life cycle ------------------------------------------------------------------------
    @property
    def speed(self) -> float:
        return self.time_scale

    @property
    def path(self) -> str:
        """The pty path (or link), or host:port for TCP."""
        return self.dev.path

    @property
    def url(self) -> str:
        """What to give the driver: the pty path or ``tcp://host:port``."""
        return self.dev.path if isinstance(self.dev, PtyDevice) else f"tcp://{self.dev.path}"

    # start(), __enter__/__exit__: TwinControl
    def close(self) -> None:
        """End the twin thread and close the device."""
        super().stop()
        self.dev.close()

    stop = close   # the name the other twins use

    # -- faults (truncate: the next scan replies cut short; stall, unplug, replug: TwinControl)
    def unstable(self, n: int = 1) -> None:
        """Answer the next ``n`` scans of the stream with status 0M (sensor unstable)."""
        with self._lock:
            self._unstable += n

    def disconnect(self) -> None:
        """Unplug: the pty pair closes and its path disappears (TCP: the port closes)."""
        self.unplug()

    def reconnect(self) -> None:
        """Plug back in: a fresh pty behind the same path; the sensor powers up again."""
        self.replug()

    def _unplug(self) -> None:
        with self._lock:
            self.dev.disconnect()

    def _replug(self) -> None:
        with self._lock:
            self._power_on()
            self._inbuf = b""
            self.dev.reconnect()

    @property
    def streaming(self) -> bool:
        return self._stream is not None

    # -- device state ----------------------------------------------------------------------
    def _power_on(self) -> None:
        self.baud: int | None = self.power_on_baud
        self._laser = False
        self._tm_mode = False
        self._stream: dict | None = None

    def clock_ms(self, at: float | None = None) -> float:
        """The device clock (ms, not wrapped) at host monotonic time ``at`` (default now)."""
        at = time.monotonic() if at is None else at
        return self.clock0_ms + (at - self._t0) * 1000.0 * self.speed

    def _stamp(self) -> int:
        return int(self.clock_ms()) % (1 << 24)

    @property
    def scan_period_s(self) -> float:
        """Wall-clock time between scans (device period divided by ``speed``)."""
        return 60.0 / self.p["scan"] / self.speed

    # -- serving ---------------------------------------------------------------------------
    def _run(self) -> None:
        while self._running:
            self._serve_requests()
            with self._lock:
                open_ = self.dev.is_open
                stalled = time.monotonic() < self._stall_until
            if not open_ or stalled:
                time.sleep(0.005)
                continue
            wait = 0.02
            if self._stream is not None:
                wait = max(0.0, min(wait, self._stream["due"] - time.monotonic()))
            try:
                data = self.dev.read(4096, wait)
                if data:
                    self._on_input(data)
                self._maybe_stream()
            except (PtyClosed, OSError):
                time.sleep(0.005)   # disconnected under our feet; wait for reconnect()

    def _rate_mismatch(self) -> bool:
        return (self.baud is not None and isinstance(self.dev, PtyDevice)
                and self.dev.host_baud() != self.baud)

    def _on_input(self, data: bytes) -> None:
        if self._rate_mismatch():            # framing errors at the wrong rate: nothing usable
            self._inbuf = b""
            return
        self._inbuf += data
        *lines, self._inbuf = self._inbuf.replace(b"\r", b"\n").split(b"\n")
        if len(self._inbuf) > 256:            # no terminator in sight: drop it
            self._inbuf = b""
        for raw in lines:
            if not raw:
                continue
            try:
                self._command(raw.decode("ascii", "replace"))
            except (PtyClosed, OSError):
                raise                        # the link itself: _run waits for reconnect()
            except Exception:                # one bad command must not end the serving thread
                self.command_errors += 1

    def _send(self, data: bytes, scan: SentScan | None = None, cut: bool = False) -> None:
        """Write with byte errors (and an optional cut) applied; record scans."""
        intact, orig = True, data
        if self._rate_mismatch():
            data = self.fault_rng.bytes(len(data))
            intact = False
        if cut and len(data) > 30:
            data = data[: int(self.fault_rng.integers(20, len(data) - 2))]
            intact = False
        if self.fault_rate > 0:
            hits = np.flatnonzero(self.fault_rng.random(len(data)) < self.fault_rate)
            if hits.size:
                buf = np.frombuffer(data, dtype=np.uint8).copy()
                buf[hits] ^= self.fault_rng.integers(1, 256, hits.size).astype(np.uint8)
                data = buf.tobytes()
                intact = False
        if scan is not None:
            scan.intact = intact
            scan.undetectable = not intact and not cut and _passes_checks(orig, data)
            self.sent.append(scan)
        self.dev.write(data, timeout=0.5)

    def _reply(self, echo: str, status: str, body: bytes = b"") -> None:
        st = status.encode("ascii")
        head = echo.encode("ascii", "replace")     # a non-ASCII command echoes as '?'
        self._send(head + b"\n" + st + sum_char(st) + b"\n" + body + b"\n")

    def _command(self, line: str) -> None:
        self.commands.append(line)
        if not self._scip2:
            if line == "SCIP2.0":
                self._scip2 = True
                self._send(b"SCIP2.0\n0\n\n")
            else:
                self._send(line.encode("ascii", "replace") + b"\nE\n\n")
            return
        cmd = line.split(";", 1)[0]
        if self._tm_mode and not cmd.startswith("TM"):
            self._reply(line, "0E")
            return
        if cmd == "QT":
            self._stream = None
            self._laser = False
            self._reply(line, "00")
        elif cmd == "BM":
            if self.bm_status != "00":
                self._reply(line, self.bm_status)
            else:
                self._reply(line, "02" if self._laser else "00")
                self._laser = True
        elif cmd in ("RS", "RT"):
            self._power_on()
            self._reply(line, "00")
        elif cmd == "VV":
            self._reply(line, "00", b"".join(info_line(k, v) for k, v in (
                ("VEND", "Hokuyo Automatic Co.,Ltd."), ("PROD", self.p["prod"]),
                ("FIRM", self.p["firm"]), ("PROT", "SCIP 2.0"), ("SERI", "H0000001"))))
        elif cmd == "PP":
            p = self.p
            self._reply(line, "00", b"".join(info_line(k, str(v)) for k, v in (
                ("MODL", self.model), ("DMIN", p["dmin"]), ("DMAX", p["dmax"]),
                ("ARES", p["ares"]), ("AMIN", p["amin"]), ("AMAX", p["amax"]),
                ("AFRT", p["afrt"]), ("SCAN", p["scan"]))))
        elif cmd == "II":
            self._reply(line, "00", b"".join(info_line(k, v) for k, v in (
                ("MODL", self.model), ("LASR", "ON" if self._laser else "OFF"),
                ("SCSP", f"Initial({self.p['scan']}[rpm])"), ("MESM", "Measuring by Normal Mode"),
                ("SBPS", "USB only"), ("TIME", encode_values(np.array([self._stamp()]),
                                                              4).decode()),
                ("STAT", "Sensor works well."))))
        elif cmd.startswith("TM") and len(cmd) == 3:
            self._time_command(line, cmd[2])
        elif cmd.startswith("SS") and len(cmd) == 8 and cmd[2:].isdigit():
            rate = int(cmd[2:])
            if rate not in (19200, 38400, 57600, 115200, 250000, 500000, 750000):
                self._reply(line, "01")
            elif self.baud is not None and rate == self.baud:
                self._reply(line, "03")       # already at that rate
            else:
                self._reply(line, "00")       # answered at the old rate, then switch
                if self.baud is not None:
                    self.baud = rate
        elif cmd[:1] in ("G", "M") and cmd[1:2] in ("D", "S", "E"):
            self._scan_command(line, cmd)
        else:
            self._reply(line, "0E")

    def _time_command(self, line: str, code: str) -> None:
        if code == "0":
            self._stream = None
            self._reply(line, "02" if self._tm_mode else "00")
            self._tm_mode = True
        elif code == "1":
            if not self._tm_mode:
                self._reply(line, "01")
                return
            t = encode_values(np.array([self._stamp()]), 4)
            self._reply(line, "00", t + sum_char(t) + b"\n")
        elif code == "2":
            self._reply(line, "00" if self._tm_mode else "03")
            self._tm_mode = False
        else:
            self._reply(line, "01")

    def _scan_command(self, line: str, cmd: str) -> None:
        m = _SCAN_CMD.match(line)
        if not m:
            self._reply(line, "0H" if len(cmd) < 12 else "0D")
            return
        kind, enc, start, end, cluster = m.group(1), m.group(2), int(m.group(3)), \
            int(m.group(4)), max(1, int(m.group(5)))
        if kind == "M" and m.group(6) is None:
            self._reply(line, "0H")
            return
        if end > self.p["amax"] or start < self.p["amin"]:
            self._reply(line, "04")
            return
        if end < start:
            self._reply(line, "05")
            return
        spec = dict(enc=enc, start=start, end=end, cluster=cluster, echo=line)
        if kind == "G":
            if not self._laser:
                self._reply(line, "10")
                return
            self._send_scan(spec, line, "00")
            return
        skip, count = int(m.group(6)), int(m.group(7))
        self._laser = True
        self._reply(line, "00")
        due = time.monotonic() + self.scan_period_s
        spec.update(skip=skip, count=count, sent=0, tick=0, due=due,
                    ms0=int(self.clock_ms(due)))
        self._stream = spec

    def _maybe_stream(self) -> None:
        s = self._stream
        now = time.monotonic()
        if s is None or now < s["due"]:
            return
        # turns happen on a fixed grid of device time (25 ms for a UTM-30LX); a scan is
        # sent when the host thread gets to it
        k = s["tick"]
        ms = s["ms0"] + k * 60000 // self.p["scan"]
        s["tick"] += 1
        s["due"] += self.scan_period_s
        if s["due"] < now:                    # fell behind (slow host): skip missed turns
            missed = int((now - s["due"]) / self.scan_period_s) + 1
            s["tick"] += missed
            s["due"] += missed * self.scan_period_s
        if k % (s["skip"] + 1):
            return
        s["sent"] += 1
        remaining = max(0, s["count"] - s["sent"]) if s["count"] else 0
        echo = s["echo"][:13] + f"{remaining:02d}" + s["echo"][15:]
        with self._lock:
            unstable = self._unstable > 0
            self._unstable -= unstable
        if unstable:                          # an error block in place of the scan
            self._reply(echo, "0M")
            return
        self._send_scan(s, echo, "99", ms)
        if s["count"] and s["sent"] >= s["count"]:
            self._stream = None

    def _measure(self, spec: dict, t: float) -> tuple[np.ndarray, np.ndarray | None]:
        """Ranges (mm, with device error codes) of the requested steps (cluster centres) as
        sensed at device time ``t`` seconds: the world's trajectory at the scan's timestamp."""
        p = self.p
        steps = np.arange(spec["start"], spec["end"] + 1, spec["cluster"], dtype=float)
        steps += (np.minimum(spec["cluster"], spec["end"] + 1 - steps) - 1) / 2.0
        angles = (steps - p["afrt"]) * 2.0 * np.pi / p["ares"]
        r = self.world.scan(t, angles, p["dmax"] / 1000.0, self.noise, self.rng)
        mm = np.round(np.nan_to_num(r, nan=0.0) * 1000.0)
        limit = 4095 if spec["enc"] == "S" else p["dmax"]
        bad = ~np.isfinite(r) | (mm > limit)
        mm = np.where(bad, 1, np.clip(mm, 0, limit)).astype(np.uint32)   # 1: no echo code
        inten = None
        if spec["enc"] == "E":
            inten = np.where(bad, 0, 4000 - np.minimum(mm // 20, 3000)).astype(np.uint32)
        return mm, inten

    def _send_scan(self, spec: dict, echo: str, status: str, ms: int | None = None) -> None:
        ms = int(self.clock_ms()) if ms is None else ms
        mm, inten = self._measure(spec, ms / 1000.0)
        ts = ms % (1 << 24)
        block = scan_reply(echo, status, ts, mm, spec["enc"], inten)
        self._send(block, SentScan(ts, True, mm, echo), cut=self._take_truncate())


def process_epoch() -> float:
    """Host monotonic time (s) at which the device clock starts when run as a process.

    ``CGAMAP_SIM_EPOCH_NS`` (monotonic ns, set by whoever starts the twin) if given; else when
    this process started (Linux /proc, 10 ms resolution), so that "just before the twin was
    started" is the clock's zero for its parent; else now.
    """
    env = os.environ.get("CGAMAP_SIM_EPOCH_NS")
    if env:
        with contextlib.suppress(ValueError):
            return int(env) / 1e9
    try:
        with open("/proc/self/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        started = int(fields[19]) / os.sysconf("SC_CLK_TCK")     # since boot, s
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - started
        if 0.0 <= age < 60.0:
            return time.monotonic() - age
    except (OSError, ValueError, IndexError, AttributeError):
        pass
    return time.monotonic()


def main(args: argparse.Namespace) -> int:
    """``cgamap sim-device hokuyo``: serve on a pty (on TCP for the Ethernet UST-10LX, or with
    ``--port`` N > 0) until SIGINT/SIGTERM.

    Prints the device path (or host:port) first.  The device clock (SCIP timestamps, and the
    trajectory time the world is sensed at) counts from :func:`process_epoch`.  SIGUSR1
    unplugs the device for 1 s (then it returns at the same path); SIGUSR2 stalls it for 2 s.
    ``--model`` (if the CLI gives one) or the environment variable ``CGAMAP_HOKUYO_MODEL``
    picks the model (UTM-30LX by default, URG-04LX, UST-10LX).
    """
    model = getattr(args, "model", None) or os.environ.get("CGAMAP_HOKUYO_MODEL", "UTM-30LX")
    port = getattr(args, "port", 0) or 0
    tcp = port > 0 or ALIASES.get(model.lower(), model) == "UST-10LX"
    tmp = tempfile.mkdtemp(prefix="cgamap-hokuyo-")
    try:
        twin = HokuyoTwin(model, getattr(args, "world", "corridor"),
                          fault_rate=getattr(args, "fault_rate", 0.0) or 0.0,
                          seed=getattr(args, "seed", 0) or 0, link=os.path.join(tmp, "ttyACM0"),
                          epoch=process_epoch(), tcp_port=port if tcp else None)
    except (ValueError, OSError) as exc:   # drivers may not import the CLI: report like it does
        os.rmdir(tmp)
        print(f"cgamap: sim-device hokuyo: {exc}", file=sys.stderr)
        return 2
    try:
        return serve_until_signal(
            lambda: twin.start().path, twin.close,
            banner=f"hokuyo twin: {twin.model}, world {twin.world.name}, fault rate "
                   f"{twin.fault_rate:g}; SIGUSR1 unplugs 1 s, SIGUSR2 stalls 2 s",
            faults=SignalFaults(twin.unplug, twin.replug, twin.stall, unplug_s=1.0))
    finally:
        with contextlib.suppress(OSError):
            os.rmdir(tmp)
