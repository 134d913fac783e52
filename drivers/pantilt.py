"""Pan-tilt head of two Dynamixel X-series servos (Protocol 2.0) through dynamixel-sdk; AX
and MX servos in Protocol 1.0 with ``protocol: 1.0`` (no SYNC_READ there: one READ per servo,
alarms from the status error byte, no REBOOT).

Joint angles are radians with 0 at the model's centre position (2048 of 0..4095 for X and MX,
512 of 0..1023 over 300° for AX) unless a joint's ``zero`` says otherwise.  Axes (DESIGN.md
camera chain, seed eqs. 17-22): **pan** turns the head about the base's +z axis (positive =
counter-clockwise seen from above, the camera looks left); **tilt** turns the head about the
pan-turned head's +y axis (y left; positive = right-handed about +y, so the camera's forward
axis dips: positive tilt looks *down*).  :meth:`PanTilt.rotors` gives ``R_pan = rotor(e_z,
pan)`` and ``R_tilt = rotor(e_y, tilt)``, to be used as ``R_pt = R_pos R_pan R_tilt``.
``sign: -1`` in a joint's config flips a servo mounted the other way round.

Start-up: open the port, ping both IDs and check the model numbers against the accepted list,
set the profile velocity.  ``move`` refuses (raises :class:`PanTiltLimitError`) a goal outside a
joint's limits before anything is sent; goals go out in one SYNC_WRITE.  ``read_state`` does a
SYNC_READ of Moving..Present Position (addresses 122-135) and of Hardware Error Status (70).
``PanTiltState.hardware_error`` packs the pan servo's status in bits 0-7 and the tilt servo's in
bits 8-15 (bit 2 overheating, 3 encoder, 4 electrical shock, 5 overload, 0 input voltage;
Protocol 1.0 alarms use the same bit positions for voltage, overheating and overload).

dynamixel-sdk workarounds, all in :class:`_Port` and :meth:`PanTilt._txrx` (devices.md §1.7):
the port is opened with a 2 ms read timeout instead of ``timeout=0`` (the SDK's receive loop
spins on ``readPort`` and holds the GIL); the packet timeout uses a configurable latency
(``latency_ms``, default 100, instead of the module constant 16 that fails under load) measured on
``time.monotonic`` (not wall time, which NTP steps); ports may be URLs (``socket://``); and after
any failed transaction the driver waits one more packet timeout and drops the input, so a late
reply is never taken for the next request's.  ``max_timeouts`` failures in a row raise
:class:`PanTiltBusError` (a bus fault, for the supervisor to restart the device).
"""

from __future__ import annotations

import logging
import math
import termios
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, fields, replace
from typing import Any

import serial
from cgamap.cga import Multivector, rotor

from .messages import ErrorCounters, PanTiltState
from .pacing import paced_reads
from .transport import parse_device_url

log = logging.getLogger(__name__)
# a vanished port (USB unplug, twin closed the pty) shows as any of these
_PORT_ERRORS = (OSError, serial.SerialException, termios.error)

HW_ERROR_BITS = {0: "input voltage", 2: "overheating", 3: "motor encoder",
                 4: "electrical shock", 5: "overload"}
_RPM = 2.0 * math.pi / 60.0


@dataclass(frozen=True)
class ServoTable:
    """Where a servo family keeps what the head needs, and its units."""

    family: str
    protocol: float
    torque: int                # Torque Enable (1 byte)
    goal: int                  # Goal Position
    goal_size: int
    speed: int                 # Profile Velocity (X) / Moving Speed (AX, MX 1.0)
    speed_size: int
    state: int                 # one read covering the moving flag and the present position
    state_len: int
    pos_off: int               # present position within that read
    pos_size: int
    moving_off: int
    hw_error: int | None       # Hardware Error Status address; None: status error byte only
    pos_per_rad: float
    center: int                # position at angle 0
    vel_unit: float            # rad/s per speed unit
    speed_max: int


X_SERIES = ServoTable("X-series", 2.0, 64, 116, 4, 112, 4, 122, 14, 10, 4, 0, 70,
                      4096.0 / (2.0 * math.pi), 2048, 0.229 * _RPM, 32767)
AX_SERIES = ServoTable("AX", 1.0, 24, 30, 2, 32, 2, 36, 11, 0, 2, 10, None,
                       1023.0 / math.radians(300.0), 512, 0.111 * _RPM, 1023)
MX_SERIES_P1 = ServoTable("MX (Protocol 1.0)", 1.0, 24, 30, 2, 32, 2, 36, 11, 0, 2, 10, None,
                          4096.0 / (2.0 * math.pi), 2048, 0.114 * _RPM, 1023)
# Model numbers (ROBOTIS e-manual) and their tables; extend ``models`` in the config to accept
# only some of them.
KNOWN_MODELS = {1000: "XH430-W210", 1010: "XH430-W350", 1020: "XM430-W350",
                1030: "XM430-W210", 1060: "XL430-W250", 1070: "XC430-W150",
                1080: "XC430-W240", 1090: "2XL430-W250", 1120: "XM540-W270",
                1130: "XM540-W150", 1190: "XL330-M077", 1200: "XL330-M288",
                12: "AX-12A", 18: "AX-18A", 300: "AX-12W",
                29: "MX-28", 310: "MX-64", 320: "MX-106"}
MODEL_TABLES = {m: (AX_SERIES if m in (12, 18, 300) else MX_SERIES_P1 if m in (29, 310, 320)
                    else X_SERIES) for m in KNOWN_MODELS}
# Protocol 1.0 status error bits that are hardware alarms (same bit positions as 2.0's
# Hardware Error Status: 0 input voltage, 2 overheating, 5 overload).
_P1_HW_BITS = 0x25


class PanTiltError(Exception):
    """The head could not be opened (absent servo, wrong model) or a command failed."""


class PanTiltLimitError(PanTiltError, ValueError):
    """A goal outside the configured joint limits (refused before anything was sent)."""


class PanTiltBusError(PanTiltError):
    """Repeated failed transactions: treat the bus as faulty."""


@dataclass(frozen=True)
class JointConfig:
    dxl_id: int
    min_rad: float
    max_rad: float
    zero: int | None = None   # servo position at angle 0 (None: the model's centre)
    sign: int = 1             # -1: servo mounted reversed

    def to_units(self, rad: float, table: ServoTable = X_SERIES) -> int:
        zero = table.center if self.zero is None else self.zero
        return round(zero + self.sign * rad * table.pos_per_rad)

    def to_rad(self, units: int, table: ServoTable = X_SERIES) -> float:
        zero = table.center if self.zero is None else self.zero
        return self.sign * (units - zero) / table.pos_per_rad


@dataclass
class PanTiltConfig:
    url: str = "/dev/ttyUSB0"
    baudrate: int | None = None            # None: from the URL (baudrate=), else 57600
    protocol: float = 2.0                  # 2.0: X-series; 1.0: AX / MX (Protocol 1.0)
    pan: JointConfig = field(default_factory=lambda: JointConfig(1, -2.6, 2.6))
    tilt: JointConfig = field(default_factory=lambda: JointConfig(2, -1.0, 1.0))
    models: tuple[int, ...] = tuple(KNOWN_MODELS)
    profile_velocity: float = 2.0          # rad/s (0: the servo's velocity limit)
    latency_ms: float = 100.0              # packet timeout = bytes on the wire + 2 latency + 2 ms
    read_timeout_s: float = 0.002          # per readPort call: bounds the SDK's receive loop
    max_timeouts: int = 5                  # failures in a row before PanTiltBusError

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PanTiltConfig:
        d = dict(d)
        kw = {k: v for k, v in d.items() if k in {f.name for f in fields(cls)}}
        for name in ("pan", "tilt"):
            if isinstance(kw.get(name), dict):
                j = dict(kw[name])
                if "id" in j:
                    j["dxl_id"] = j.pop("id")
                kw[name] = JointConfig(**j)
        if "models" in kw:
            kw["models"] = tuple(kw["models"])
        return cls(**kw)

    def with_ids(self, pan_id: int, tilt_id: int) -> PanTiltConfig:
        return replace(self, pan=replace(self.pan, dxl_id=pan_id),
                       tilt=replace(self.tilt, dxl_id=tilt_id))


# a device path, serial://, a TCP serial server, and pyserial's URL handlers that make sense
# for a servo bus
_SCHEMES = ("serial", "tcp", "socket", "loop", "rfc2217", "spy", "alt")


def _port_name(url: str) -> tuple[str, int | None]:
    """What pyserial opens (a path or a pyserial URL) and the URL's baud rate, if any.
    Raises PanTiltError naming the URL for anything the port could not be opened with."""
    u = parse_device_url(url, _SCHEMES, PanTiltError)
    if u.spy:
        log.warning("%s: no byte tracing on the servo bus here (spy+ / trace=1 ignored; "
                    "pyserial's spy:// traces)", url)
    return (f"socket://{u.address}" if u.is_network else u.path), u.baud


def _make_port_class():
    from dynamixel_sdk import PortHandler

    class _Port(PortHandler):
        """PortHandler with a blocking read timeout, a configurable latency, a monotonic clock
        and URL support (devices.md §1.7 pitfalls 1, 2, 6)."""

        def __init__(self, name: str, latency_ms: float, read_timeout_s: float) -> None:
            super().__init__(name)
            self.latency_ms = latency_ms
            self.read_timeout_s = read_timeout_s

        def setupPort(self, cflag_baud):
            if self.is_open:
                self.closePort()
            self.ser = serial.serial_for_url(self.port_name, baudrate=self.baudrate,
                                             bytesize=serial.EIGHTBITS,
                                             timeout=self.read_timeout_s, exclusive=True)
            self.is_open = True
            self.ser.reset_input_buffer()
            self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
            return True

        def setBaudRate(self, baudrate):
            # pyserial takes any rate (and a pty ignores it): no SDK whitelist
            self.baudrate = baudrate
            return self.setupPort(baudrate)

        def setPacketTimeout(self, packet_length):
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = (self.tx_time_per_byte * packet_length
                                   + 2.0 * self.latency_ms + 2.0)

        def setPacketTimeoutMillis(self, msec):
            self.packet_start_time = self.getCurrentTime()
            self.packet_timeout = max(msec, 2.0 * self.latency_ms + 2.0)

        def getCurrentTime(self):
            return time.monotonic() * 1000.0

    return _Port


class PanTilt:
    """The head.  ``open()`` checks the servos; use as a context manager."""

    def __init__(self, config: PanTiltConfig | str, **params: Any) -> None:
        if isinstance(config, str):   # url plus config keys (the daemon's device params)
            config = PanTiltConfig.from_dict({**params, "url": config})
        self.config = config
        self.errors = ErrorCounters()
        self.models: dict[int, int] = {}
        self.tables: dict[int, ServoTable] = {}
        self.last_hw_error: dict[int, int] = {}
        self._port = None
        self._ph = None
        self._seq = 0
        self._fails = 0
        self._port_name, baud = _port_name(config.url)
        self.baudrate = config.baudrate or baud or 57600

    @property
    def ids(self) -> tuple[int, int]:
        return self.config.pan.dxl_id, self.config.tilt.dxl_id

    # -- the one place that talks to the SDK --------------------------------------------
    def _txrx(self, what: str, call: Callable[[], Any], dxl_id: int | None = None) -> Any:
        """Run one SDK call returning ``result`` or ``(…, result, error)``; count failures,
        resynchronise after them; returns the call's value, or None if it failed."""
        from dynamixel_sdk import COMM_RX_CORRUPT, COMM_RX_TIMEOUT, COMM_SUCCESS

        self._check_open(what)
        try:
            out = call()
        except _PORT_ERRORS as exc:
            self.errors.disconnects += 1
            raise PanTiltBusError(f"{self.config.url}: {what}: {exc}") from exc
        res, err = (out, 0) if isinstance(out, int) else (out[-2], out[-1])
        if res != COMM_SUCCESS:
            if res == COMM_RX_CORRUPT:
                self.errors.checksum += 1
            elif res == COMM_RX_TIMEOUT:
                self.errors.timeout += 1
            else:
                self.errors.framing += 1
            log.info("%s: %s: %s", self.config.url, what, self._ph.getTxRxResult(res))
            self._resync()
            self._fails += 1
            if self._fails >= self.config.max_timeouts:
                self._fails = 0
                raise PanTiltBusError(f"{self.config.url}: {what}: "
                                      f"{self.config.max_timeouts} failed transactions in a row")
            return None
        self._fails = 0
        if err:
            self._note_status_error(what, dxl_id, err)
        return out

    def _check_open(self, what: str) -> None:
        if self._port is None or not self._port.is_open or self._ph is None:
            raise PanTiltError(f"{self.config.url}: {what}: the head is not open")

    def _note_status_error(self, what: str, dxl_id: int | None, err: int) -> None:
        self.errors.device += 1  # bit 7 (alert): read_state reads address 70 for the cause
        if err & 0x7F:
            log.info("%s: %s (id %s): %s", self.config.url, what, dxl_id,
                     self._ph.getRxPacketError(err & 0x7F))

    def _resync(self) -> None:
        """Late-reply rule: wait one more packet timeout, then drop whatever came in."""
        time.sleep((2.0 * self.config.latency_ms + 2.0) / 1000.0)
        try:
            self._port.clearPort()
        except _PORT_ERRORS:
            pass
        self._port.is_using = False

    # -- life cycle ---------------------------------------------------------------------
    def open(self) -> PanTilt:
        from dynamixel_sdk import PacketHandler

        port_cls = _make_port_class()
        self._port = port_cls(self._port_name, self.config.latency_ms,
                              self.config.read_timeout_s)
        self._port.baudrate = self.baudrate
        try:
            self._port.openPort()
        except (OSError, serial.SerialException, ValueError, KeyError) as exc:  # KeyError: loop://?x
            raise PanTiltError(f"{self.config.url}: cannot open: {exc}") from exc
        if self.config.protocol not in (1.0, 2.0):
            raise PanTiltError(f"{self.config.url}: protocol {self.config.protocol}: 1.0 or 2.0")
        self._ph = PacketHandler(self.config.protocol)
        try:
            for joint, name in ((self.config.pan, "pan"), (self.config.tilt, "tilt")):
                model = None
                for _ in range(3):   # a noisy line may eat one ping
                    model = self.ping(joint.dxl_id)
                    if model is not None:
                        break
                if model is None:
                    raise PanTiltError(f"{self.config.url}: {name} servo id {joint.dxl_id} "
                                       "does not answer ping")
                table = MODEL_TABLES.get(model)
                if model not in self.config.models or table is None \
                        or table.protocol != self.config.protocol:
                    raise PanTiltError(f"{self.config.url}: {name} servo id {joint.dxl_id} is "
                                       f"model {model}, not an accepted Protocol "
                                       f"{self.config.protocol} model")
                self.models[joint.dxl_id] = model
                self.tables[joint.dxl_id] = table
            self.set_profile_velocity(self.config.profile_velocity)
        except PanTiltError:
            self.close()
            raise
        return self

    def close(self) -> None:
        if self._port is not None and self._port.is_open:
            self._port.closePort()

    def __enter__(self) -> PanTilt:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- commands -----------------------------------------------------------------------
    def ping(self, dxl_id: int) -> int | None:
        """Model number of a servo, or None if it did not answer (counted)."""
        out = self._txrx("ping", lambda: self._ph.ping(self._port, dxl_id), dxl_id)
        return None if out is None else out[0]

    def _sync_write(self, what: str, addr: int, size: int, values: dict[int, int]) -> bool:
        from dynamixel_sdk import GroupSyncWrite

        self._check_open(what)
        gsw = GroupSyncWrite(self._port, self._ph, addr, size)
        for dxl_id, v in values.items():
            gsw.addParam(dxl_id, list((int(v) & ((1 << 8 * size) - 1)).to_bytes(size, "little")))
        return self._txrx(what, gsw.txPacket) is not None

    def _write_each(self, what: str, addr: int | Callable[[ServoTable], tuple[int, int]],
                    size: int, values: dict[int, int]) -> bool:
        """Acknowledged writes (one per servo), so refusals (status errors) are seen.
        ``addr`` may be a function of the servo's table giving (address, size)."""
        ok = True
        for dxl_id, v in values.items():
            a, n = addr(self.tables[dxl_id]) if callable(addr) else (addr, size)
            fn = {1: "write1ByteTxRx", 2: "write2ByteTxRx", 4: "write4ByteTxRx"}[n]
            out = self._txrx(what, lambda i=dxl_id, v=v, a=a, n=n, fn=fn: getattr(self._ph, fn)(
                self._port, i, a, int(v) & ((1 << 8 * n) - 1)), dxl_id)
            ok = ok and out is not None and out[-1] == 0
        return ok

    def torque(self, on: bool) -> bool:
        """Torque on or off for both servos; False if a servo refused (e.g. in shutdown)."""
        return self._write_each("torque", lambda t: (t.torque, 1), 1,
                                {i: int(on) for i in self.ids})

    def set_profile_velocity(self, rad_s: float) -> bool:
        """Profile velocity (X) or moving speed (AX/MX), rad/s; 0: the servo's maximum."""
        values = {}
        for i in self.ids:
            t = self.tables[i]
            values[i] = 0 if rad_s <= 0 else min(t.speed_max, max(1, round(rad_s / t.vel_unit)))
        return self._write_each("profile velocity", lambda t: (t.speed, t.speed_size), 0,
                                values)

    def check_goal(self, pan: float, tilt: float) -> None:
        """Raise PanTiltLimitError unless both angles are finite and within the limits."""
        for name, j, v in (("pan", self.config.pan, pan), ("tilt", self.config.tilt, tilt)):
            if not (math.isfinite(v) and j.min_rad <= v <= j.max_rad):
                raise PanTiltLimitError(f"{name} goal {v:.4f} rad outside "
                                        f"[{j.min_rad:.4f}, {j.max_rad:.4f}]")

    def move(self, pan: float, tilt: float) -> bool:
        """Send goal angles (rad) in one SYNC_WRITE; limits checked first (nothing sent if out)."""
        self.check_goal(pan, tilt)
        self._check_open("goal position")
        pan_j, tilt_j = self.config.pan, self.config.tilt
        tp, tt = self.tables[pan_j.dxl_id], self.tables[tilt_j.dxl_id]
        goals = {pan_j.dxl_id: pan_j.to_units(pan, tp), tilt_j.dxl_id: tilt_j.to_units(tilt, tt)}
        if (tp.goal, tp.goal_size) == (tt.goal, tt.goal_size):
            return self._sync_write("goal position", tp.goal, tp.goal_size, goals)
        return self._write_each("goal position", lambda t: (t.goal, t.goal_size), 0, goals)

    def reboot(self) -> bool:
        """REBOOT both servos (clears a hardware error; torque comes back off).  Protocol 2.0
        only: a Protocol 1.0 servo leaves shutdown when its cause is gone."""
        if self.config.protocol != 2.0:
            raise PanTiltError(f"{self.config.url}: reboot needs Protocol 2.0")
        ok = True
        for i in self.ids:
            ok = self._txrx("reboot", lambda i=i: self._ph.reboot(self._port, i), i) is not None \
                and ok
        self.last_hw_error.clear()
        return ok

    # -- state ----------------------------------------------------------------------------
    def _sync_read(self, what: str, addr: int, size: int) -> dict[int, bytes] | None:
        from dynamixel_sdk import GroupSyncRead

        self._check_open(what)
        gsr = GroupSyncRead(self._port, self._ph, addr, size)
        for i in self.ids:
            gsr.addParam(i)
        if self._txrx(what, gsr.txRxPacket) is None:
            return None
        return {i: bytes(gsr.data_dict[i]) for i in self.ids}

    def _read_each(self, what: str) -> dict[int, bytes] | None:
        """Protocol 1.0 has no SYNC_READ: one READ per servo; alarms come in its error byte."""
        self._check_open(what)
        data = {}
        for i in self.ids:
            t = self.tables[i]
            out = self._txrx(what, lambda i=i, t=t: self._ph.readTxRx(
                self._port, i, t.state, t.state_len), i)
            if out is None:
                return None
            data[i] = bytes(out[0])
            self.last_hw_error[i] = out[-1] & _P1_HW_BITS
        return data

    def read_state(self) -> PanTiltState | None:
        """Present angles, moving flag and hardware error status; None after a counted error."""
        pan_id, tilt_id = self.ids
        tp, tt = self.tables.get(pan_id, X_SERIES), self.tables.get(tilt_id, X_SERIES)
        if tp.protocol == 2.0 and tp == tt:
            data = self._sync_read("present position", tp.state, tp.state_len)
            if data is None:
                return None
            stamp = time.monotonic_ns()
            hw = self._sync_read("hardware error status", tp.hw_error, 1)
            if hw is not None:
                for i in self.ids:
                    self.last_hw_error[i] = hw[i][0]
                if any(hw[i][0] for i in self.ids):
                    self.errors.device += 1
        else:
            data = self._read_each("present position")
            if data is None:
                return None
            stamp = time.monotonic_ns()

        def angle(joint: JointConfig) -> float:
            t = self.tables.get(joint.dxl_id, X_SERIES)
            raw = data[joint.dxl_id][t.pos_off:t.pos_off + t.pos_size]
            return joint.to_rad(int.from_bytes(raw, "little", signed=t.pos_size == 4), t)

        def moving(i: int) -> bool:
            return bool(data[i][self.tables.get(i, X_SERIES).moving_off])

        packed = self.last_hw_error.get(pan_id, 0) | self.last_hw_error.get(tilt_id, 0) << 8
        self._seq += 1
        return PanTiltState(seq=self._seq, stamp_ns=stamp, pan=angle(self.config.pan),
                            tilt=angle(self.config.tilt),
                            moving=moving(pan_id) or moving(tilt_id),
                            hardware_error=packed, errors=self.errors.as_dict())

    def poll(self, rate_hz: float = 20.0, count: int | None = None,
             stop: Any | None = None) -> Iterator[PanTiltState]:
        """read_state at ``rate_hz`` on absolute deadlines (missed slots skipped and counted as
        ``dropped``); yields each successful read.  ``stop``: a threading.Event."""
        return paced_reads(self.read_state, rate_hz, self.errors, count=count, stop=stop)

    def wait_until_reached(self, pan: float, tilt: float, tol: float = 0.01,
                           timeout: float = 10.0, period: float = 0.02) -> PanTiltState | None:
        """Poll until both joints are within ``tol`` of the goal (and still); None on timeout."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            st = self.read_state()
            if (st is not None and abs(st.pan - pan) <= tol and abs(st.tilt - tilt) <= tol
                    and not st.moving):
                return st
            time.sleep(period)
        return None

    def rotors(self, state: PanTiltState | None = None) -> tuple[Multivector, Multivector]:
        """(R_pan, R_tilt) of the camera chain: pan about +z, tilt about +y (module docstring)."""
        st = state if state is not None else self.read_state()
        if st is None:
            raise PanTiltError(f"{self.config.url}: no state to make rotors from")
        return pan_tilt_rotors(st.pan, st.tilt)


def pan_tilt_rotors(pan: float, tilt: float) -> tuple[Multivector, Multivector]:
    """R_pan = rotor(e_z, pan), R_tilt = rotor(e_y, tilt) (seed eqs. 17-22)."""
    return rotor([0.0, 0.0, 1.0], pan), rotor([0.0, 1.0, 0.0], tilt)


def describe_hw_error(bits: int) -> str:
    """Names of the set Hardware Error Status bits of one servo."""
    names = [n for b, n in HW_ERROR_BITS.items() if bits >> b & 1]
    return ", ".join(names) if names else "none"
