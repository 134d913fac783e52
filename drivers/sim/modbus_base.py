"""Twin of a differential-drive motor controller: a pymodbus server (Modbus TCP on 127.0.0.1,
or RTU over a pty) serving the default register map of :mod:`cgamap.drivers.modbus_base`.

The encoder registers integrate the wheel speeds in simulated time (wall time times
``time_scale``): speeds come from the set-point holding registers or from a script of
piecewise-constant segments ``(duration_s, left_rad_s, right_rad_s)``.  Each read advances the
simulation to "now", splitting at segment boundaries, so the integration is exact.  Errors of a
real base are configurable: ``slip`` (fraction of wheel rotation that does not move the ground,
per wheel) and ``bias`` (encoder scale error, per wheel).  The ground truth pose (exact arcs of
the ground motion) is :meth:`ModbusBaseTwin.true_pose`.

Faults (:meth:`ModbusBaseTwin.set_fault`): ``"no_reply"`` (requests are dropped), ``"slow"``
(replies after ``delay_s``, late for a client with a shorter timeout) and ``"exception"``
(exception response 4, device failure); ``None`` ends the fault.

``response_delay_s`` (config, default 0) holds every answer that long after the counters were
sampled at the request's arrival, like a controller on a slow bus or busy with its loop;
:attr:`ModbusBaseTwin.samples` keeps the ``time.monotonic_ns()`` of each input-register sample
(the newest 1000), so an in-process test can compare a driver's stamps with them.

RTU: the server opens one end of a pty pair joined to a second pty by a relay thread; clients
open the second pty's path (pymodbus opens serial ports exclusively, so one pty cannot serve
both ends).  ``fault_rate`` flips reply bytes in the relay with that probability (line noise;
RTU only, the CRC catches it).
"""

from __future__ import annotations

import asyncio
import math
import random
import select
import threading
import time
from collections import deque
from dataclasses import dataclass, field

from ..modbus_base import RegisterMap, encode_registers
from .pty_device import PtyDevice
from .twin import flip_bytes, serve_until_signal

_INPUT_SPAN = 16
_HOLDING_SPAN = 16


@dataclass
class BaseTwinConfig:
    wheel_radius: float = 0.05
    track_width: float = 0.30
    ticks_per_rev: float = 4096.0
    slip: tuple[float, float] = (0.0, 0.0)      # left, right: ground = (1 - slip) * wheel
    bias: tuple[float, float] = (0.0, 0.0)      # left, right: ticks = (1 + bias) * true ticks
    encoder_offset: int = 0                     # raw count at rest (start near a wrap to test it)
    time_scale: float = 1.0                     # simulated seconds per wall second
    script: list[tuple[float, float, float]] | None = None  # segments; None: use set-points
    loop_script: bool = False
    device_id: int = 1
    registers: RegisterMap = field(default_factory=RegisterMap)
    response_delay_s: float = 0.0               # answer this long after sampling the counters


def _arc(pose: tuple[float, float, float], s_left: float, s_right: float,
         track: float) -> tuple[float, float, float]:
    """Pose after both wheels rolled s_left, s_right (m) at a constant ratio (exact arc)."""
    x, y, th = pose
    ds = 0.5 * (s_left + s_right)
    dth = (s_right - s_left) / track
    if abs(dth) < 1e-12:
        fx, fy = ds, ds * dth / 2.0
    else:
        fx, fy = ds * math.sin(dth) / dth, ds * 2.0 * math.sin(dth / 2.0) ** 2 / dth
    c, s = math.cos(th), math.sin(th)
    th2 = math.remainder(th + dth, 2.0 * math.pi)
    return x + c * fx - s * fy, y + s * fx + c * fy, th2


class ModbusBaseTwin:
    """The simulated controller; ``start()`` serves it, ``stop()`` ends it."""

    def __init__(self, config: BaseTwinConfig | None = None, fault_rate: float = 0.0,
                 seed: int = 0) -> None:
        self.config = config or BaseTwinConfig()
        self.fault_rate = float(fault_rate)   # RTU only: probability per reply byte of a flip
        self.seed = seed
        self._lock = threading.Lock()
        self._pose = (0.0, 0.0, 0.0)
        self._phi = [0.0, 0.0]                # wheel angles (rad)
        self._cmd = [0.0, 0.0]                # commanded wheel speeds (rad/s)
        self._speed = [0.0, 0.0]              # speeds in the last step
        self._t_sim = 0.0
        self._script_t0 = 0.0                 # simulated time at which the script started
        self._t_wall: float | None = None
        self._estop = False
        self.fault: str | None = None
        self.delay_s = 0.5
        self.requests = 0
        self.samples: deque[int] = deque(maxlen=1000)   # monotonic ns of input-register samples
        self.address = ""
        self.url = ""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server = None
        self._thread: threading.Thread | None = None
        self._ptys: list[PtyDevice] = []          # RTU: the server's and the client's pty
        self._relay: threading.Thread | None = None
        self._relaying = False

    # -- simulation ---------------------------------------------------------------------
    def _speeds_at(self, t: float) -> tuple[tuple[float, float], float]:
        """Wheel speeds at simulated time t, and how long they stay so (inf: until changed)."""
        script = self.config.script
        if not script:
            return (self._cmd[0], self._cmd[1]), math.inf
        t -= self._script_t0
        total = sum(seg[0] for seg in script)
        if self.config.loop_script and total > 0:
            t = t % total
        acc = 0.0
        for dur, wl, wr in script:
            if t < acc + dur:
                return (wl, wr), acc + dur - t
            acc += dur
        return (0.0, 0.0), math.inf

    def _advance(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        if self._t_wall is None:
            self._t_wall = now
        dt = (now - self._t_wall) * self.config.time_scale
        self._t_wall = now
        cfg = self.config
        while dt > 1e-12:
            (wl, wr), left = self._speeds_at(self._t_sim)
            h = min(dt, max(left, 1e-9))
            self._phi[0] += wl * h
            self._phi[1] += wr * h
            sl = (1.0 - cfg.slip[0]) * cfg.wheel_radius * wl * h
            sr = (1.0 - cfg.slip[1]) * cfg.wheel_radius * wr * h
            self._pose = _arc(self._pose, sl, sr, cfg.track_width)
            self._speed = [wl, wr]
            self._t_sim += h
            dt -= h
        if self.config.script and self._speeds_at(self._t_sim)[1] == math.inf:
            self._speed = [0.0, 0.0]

    def true_pose(self) -> tuple[float, float, float]:
        """Ground-truth (x, y, theta) of the base now."""
        with self._lock:
            self._advance()
            return self._pose

    def sim_time(self) -> float:
        with self._lock:
            self._advance()
            return self._t_sim

    def script_done(self) -> bool:
        """True once a (non-looping) script has run out."""
        with self._lock:
            self._advance()
            return bool(self.config.script) and self._speeds_at(self._t_sim)[1] == math.inf

    def run_script(self, script: list[tuple[float, float, float]], loop: bool = False) -> None:
        """Start a script of (duration_s, left_rad_s, right_rad_s) segments now (a client that
        has read the encoders first then sees the whole drive)."""
        with self._lock:
            self._advance()
            self.config.script = list(script)
            self.config.loop_script = loop
            self._script_t0 = self._t_sim

    def set_estop(self, on: bool) -> None:
        with self._lock:
            self._estop = bool(on)

    def set_fault(self, kind: str | None, delay_s: float | None = None) -> None:
        if kind not in (None, "no_reply", "slow", "exception"):
            raise ValueError(f"modbus twin fault {kind!r}: none, no_reply, slow or exception")
        if delay_s is not None:
            self.delay_s = float(delay_s)
        self.fault = kind

    def encoder_raw(self) -> tuple[int, int]:
        """Counts as the controller holds them (before wrapping to the register width)."""
        cfg = self.config
        k = cfg.ticks_per_rev / (2.0 * math.pi)
        return (round((1.0 + cfg.bias[0]) * self._phi[0] * k) + cfg.encoder_offset,
                round((1.0 + cfg.bias[1]) * self._phi[1] * k) + cfg.encoder_offset)

    def _input_registers(self) -> dict[int, int]:
        regs = self.config.registers
        out: dict[int, int] = {}

        def put(f, raw: int) -> None:
            if f is None:
                return
            for i, w in enumerate(encode_registers(raw, f.words, f.word_order)):
                out[f.address + i] = w

        left, right = self.encoder_raw()
        put(regs.left_ticks, left)
        put(regs.right_ticks, right)
        for f, i in ((regs.left_speed, 0), (regs.right_speed, 1)):
            if f is not None:
                put(f, round((1.0 + self.config.bias[i]) * self._speed[i] / f.scale))
        if regs.status is not None:
            bit = regs.estop_bit if regs.estop_bit is not None else 0
            put(regs.status, int(self._estop) << bit)
        return out

    # -- the Modbus side ----------------------------------------------------------------
    async def _action(self, fc, start, address, count, registers, set_values):
        from pymodbus.constants import ExcCodes
        from pymodbus.exceptions import NoSuchIdException

        self.requests += 1
        fault = self.fault
        if fault == "no_reply":
            raise NoSuchIdException("twin fault: no reply")  # server drops the request
        if fault == "slow":
            await asyncio.sleep(self.delay_s)
        if fault == "exception":
            return ExcCodes.DEVICE_FAILURE
        with self._lock:
            now = time.monotonic_ns()
            self._advance(now * 1e-9)
            if fc == 4:
                self.samples.append(now)
                for addr, w in self._input_registers().items():
                    if 0 <= addr - start < len(registers):
                        registers[addr - start] = w
            elif set_values is not None and fc in (6, 16):
                regs = self.config.registers
                merged = list(registers)
                vals = set_values if isinstance(set_values, list) else [set_values]
                merged[address - start:address - start + len(vals)] = [int(v) for v in vals]
                for i, f in enumerate((regs.left_setpoint, regs.right_setpoint)):
                    if f is not None:
                        self._cmd[i] = f.raw(merged, start) * f.scale
        if self.config.response_delay_s > 0:
            # the server builds the reply from ``registers`` after this returns; one client
            # at a time, so nothing overwrites them while the answer is held
            await asyncio.sleep(self.config.response_delay_s)
        return None

    def _device(self):
        from pymodbus.simulator import DataType, SimData, SimDevice

        bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        hold = [SimData(0, count=_HOLDING_SPAN, values=0, datatype=DataType.REGISTERS)]
        inp = [SimData(0, count=_INPUT_SPAN, values=0, datatype=DataType.REGISTERS)]
        return SimDevice(id=self.config.device_id, simdata=(bits, list(bits), hold, inp),
                         action=self._action)

    def start(self, rtu: bool = False, port: int = 0, timeout: float = 10.0,
              rtu_over_tcp: bool = False) -> str:
        """Serve in a background thread; returns ``host:port`` or the client pty path.
        ``rtu_over_tcp``: RTU framing on the TCP port (url ``rtu+tcp://``, a serial-to-Ethernet
        gateway in transparent mode)."""
        ready = threading.Event()
        err: list[BaseException] = []
        serial_path = self._open_ptys() if rtu else None

        async def serve() -> None:
            from pymodbus import FramerType
            from pymodbus.server import ModbusSerialServer, ModbusTcpServer

            try:
                if rtu:
                    self._server = ModbusSerialServer(
                        self._device(), framer=FramerType.RTU, port=serial_path,
                        baudrate=115200, ignore_missing_devices=True)
                else:
                    framer = FramerType.RTU if rtu_over_tcp else FramerType.SOCKET
                    self._server = ModbusTcpServer(self._device(), address=("127.0.0.1", port),
                                                   framer=framer, ignore_missing_devices=True)
                await self._server.serve_forever(background=True)
                if not rtu:
                    p = self._server.transport.sockets[0].getsockname()[1]
                    scheme = "rtu+tcp" if rtu_over_tcp else "tcp"
                    self.address, self.url = f"127.0.0.1:{p}", f"{scheme}://127.0.0.1:{p}"
            except BaseException as exc:  # reported to start()'s caller
                err.append(exc)
                ready.set()
                return
            ready.set()
            await self._server.serving

        def run() -> None:
            self._loop = asyncio.new_event_loop()
            asyncio.set_event_loop(self._loop)
            try:
                self._loop.run_until_complete(serve())
                pending = asyncio.all_tasks(self._loop)  # e.g. replies held by a "slow" fault
                for task in pending:
                    task.cancel()
                if pending:
                    self._loop.run_until_complete(
                        asyncio.gather(*pending, return_exceptions=True))
            finally:
                self._loop.close()

        import logging
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # faults are deliberate
        self._thread = threading.Thread(target=run, name="modbus-twin", daemon=True)
        self._thread.start()
        if not ready.wait(timeout) or err:
            self.stop()
            raise RuntimeError(f"modbus twin did not start: {err[0] if err else 'timeout'}")
        if rtu:
            time.sleep(0.05)  # the serial server opens its port from the loop
        with self._lock:
            self._t_wall = time.monotonic()
        return self.address

    def _open_ptys(self) -> str:
        """Two ptys joined by a relay thread (line noise on the replies with ``fault_rate``);
        returns the path the server opens (clients open :attr:`url`)."""
        srv, cli = PtyDevice(), PtyDevice()
        self._ptys = [srv, cli]
        self.address = self.url = cli.path
        rng = random.Random(self.seed)
        self._relaying = True

        def relay() -> None:
            peer = {srv.master: (srv, cli), cli.master: (cli, srv)}
            try:
                while self._relaying:     # the timeout bounds how long stop() waits
                    ready, _, _ = select.select(list(peer), [], [], 0.05)
                    for fd in ready:
                        src, dst = peer[fd]
                        data = src.read(4096, 0.0)
                        if src is srv and self.fault_rate > 0:
                            data = flip_bytes(data, self.fault_rate, rng)
                        dst.write(data)
            except OSError:               # PtyClosed included: a pty failed under the relay
                return

        self._relay = threading.Thread(target=relay, name="modbus-twin-relay", daemon=True)
        self._relay.start()
        return srv.path

    def stop(self) -> None:
        if self._loop is not None and self._server is not None and self._loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
            try:
                fut.result(timeout=5)
            except Exception:  # already closing
                pass
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._relaying = False
        if self._relay is not None:
            self._relay.join(timeout=5)
        for pty in self._ptys:
            pty.close()
        self._ptys = []

    def __enter__(self) -> ModbusBaseTwin:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def square_script(side: float, speed: float, wheel_radius: float, track: float,
                  pause: float = 0.05) -> list[tuple[float, float, float]]:
    """Segments that drive a counter-clockwise square (side m, wheel speed rad/s), with short
    stops between legs and turns."""
    w = speed
    v = w * wheel_radius
    turn_time = (math.pi / 2.0) * (track / 2.0) / v
    segs: list[tuple[float, float, float]] = []
    for _ in range(4):
        segs += [(side / v, w, w), (pause, 0.0, 0.0), (turn_time, -w, w), (pause, 0.0, 0.0)]
    return segs


def circle_script(radius: float, speed: float, wheel_radius: float, track: float,
                  turns: float = 1.0) -> list[tuple[float, float, float]]:
    """One segment driving ``turns`` counter-clockwise circles of ``radius`` at ``speed`` m/s."""
    w = speed / radius
    wl = w * (radius - track / 2.0) / wheel_radius
    wr = w * (radius + track / 2.0) / wheel_radius
    return [(turns * 2.0 * math.pi / w, wl, wr)]


def main(args) -> int:
    """``cgamap sim-device modbus-base [--rtu] [--port N]``: serve until SIGINT/SIGTERM."""
    # response_delay: read if the CLI offers it (``--response-delay``, seconds)
    cfg = BaseTwinConfig(response_delay_s=float(getattr(args, "response_delay", 0.0) or 0.0))
    twin = ModbusBaseTwin(cfg, fault_rate=float(getattr(args, "fault_rate", 0.0) or 0.0),
                          seed=int(getattr(args, "seed", 0) or 0))
    rtu, port = bool(getattr(args, "rtu", False)), int(getattr(args, "port", 0))
    return serve_until_signal(lambda: twin.start(rtu=rtu, port=port), twin.stop)
