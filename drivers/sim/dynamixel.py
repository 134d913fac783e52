"""Twin of a Dynamixel bus: X-series servos (Protocol 2.0), or AX-12 servos (Protocol 1.0,
``protocol=1.0``), answering on one pty.

Speaks the real wire format (``devices.md`` §1.3-1.5): header ``FF FF FD 00``, ID, length,
instruction, byte-stuffed parameters, CRC-16 (poly 0x8005).  Served instructions: PING
(unicast and broadcast), READ, WRITE, REBOOT, SYNC_READ (one status packet per listed servo, in
list order) and SYNC_WRITE.  Each servo has a 1 KiB control table with the X-series layout; EEPROM
(below address 64) is write-protected while torque is on (error 7, access), and a goal position
outside the position limits (48/52) is refused (error 6, data limit).  With torque on, the
present position moves toward the goal at the profile velocity (address 112, 0.229 rev/min per
unit; 0 means the velocity limit), so a move takes the time it would on a real head.

Faults (:meth:`DynamixelBusTwin.set_fault`, optionally for some IDs only):
``"no_reply"`` (instructions are ignored), ``"late"`` (replies sent ``delay_s`` late, after the
SDK has given up: the classic desynchronising late reply), ``"corrupt_crc"`` (replies carry a
wrong CRC) and ``"hardware_error"`` (Hardware Error Status bit 2, overheating: the alert bit 7 is
set in every status packet and torque drops, until a REBOOT instruction or ``set_fault(None)``).
``fault_rate`` (``cgamap sim-device dynamixel-pantilt --fault-rate P --seed S``) flips each sent
byte with probability P: line noise.
"""

from __future__ import annotations

import heapq
import math
import random
import time
from dataclasses import dataclass, field

from .pty_device import PtyClosed, PtyDevice
from .twin import TwinControl, flip_bytes, serve_until_signal

# -- protocol 2.0 framing (pure) --------------------------------------------------------------

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
INST_PING, INST_READ, INST_WRITE, INST_REBOOT = 0x01, 0x02, 0x03, 0x08
INST_SYNC_READ, INST_SYNC_WRITE, INST_STATUS = 0x82, 0x83, 0x55
ERR_RESULT, ERR_INSTRUCTION, ERR_CRC, ERR_RANGE, ERR_LENGTH, ERR_LIMIT, ERR_ACCESS = range(1, 8)
ALERT = 0x80


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
        table.append(crc)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes) -> int:
    """CRC-16/BUYPASS (poly 0x8005, init 0, no reflection): the Protocol 2.0 checksum."""
    crc = 0
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert FD after every FF FF FD in the instruction/parameter bytes."""
    out = bytearray()
    for b in body:
        out.append(b)
        if out[-3:] == b"\xff\xff\xfd":
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Drop the FD that follows FF FF FD (inverse of :func:`stuff`)."""
    out = bytearray()
    i = 0
    while i < len(body):
        out.append(body[i])
        if out[-3:] == b"\xff\xff\xfd" and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1
        i += 1
    return bytes(out)


def build_packet(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """A complete packet: header, ID, length, stuffed instruction + params, CRC (LE)."""
    body = stuff(bytes([instruction]) + bytes(params))
    head = HEADER + bytes([dxl_id]) + (len(body) + 2).to_bytes(2, "little")
    pkt = head + body
    return pkt + crc16(pkt).to_bytes(2, "little")


def status_packet(dxl_id: int, error: int, params: bytes = b"") -> bytes:
    return build_packet(dxl_id, INST_STATUS, bytes([error]) + bytes(params))


def parse_packets(buf: bytearray) -> list[tuple[int, int, bytes, bool]]:
    """Take complete packets off the front of ``buf``: (id, instruction, params, crc_ok).

    Garbage before a header is dropped; an incomplete packet stays in ``buf``."""
    out = []
    while True:
        start = buf.find(HEADER)
        if start < 0:
            del buf[:max(0, len(buf) - 3)]  # keep a possible partial header
            return out
        del buf[:start]
        if len(buf) < 7:
            return out
        length = int.from_bytes(buf[5:7], "little")
        if length < 3 or length > 1024:
            del buf[:1]
            continue
        total = 7 + length
        if len(buf) < total:
            return out
        pkt = bytes(buf[:total])
        del buf[:total]
        ok = crc16(pkt[:-2]) == int.from_bytes(pkt[-2:], "little")
        body = unstuff(pkt[7:-2])
        out.append((pkt[4], body[0], body[1:], ok))


# -- protocol 1.0 framing (AX / MX servos) ------------------------------------------------------

def checksum1(body: bytes) -> int:
    """Protocol 1.0 checksum: ~(ID + LEN + INST/ERR + params) & 0xFF."""
    return ~sum(body) & 0xFF


def build_packet1(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """FF FF ID LEN INST PARAMS CHK (LEN = params + 2); also status packets (INST = error)."""
    body = bytes([dxl_id, len(params) + 2, instruction]) + bytes(params)
    return b"\xff\xff" + body + bytes([checksum1(body)])


def parse_packets1(buf: bytearray) -> list[tuple[int, int, bytes, bool]]:
    """Complete Protocol 1.0 packets off the front of ``buf``: (id, inst, params, chk_ok)."""
    out = []
    while True:
        start = buf.find(b"\xff\xff")
        if start < 0:
            del buf[:max(0, len(buf) - 1)]
            return out
        del buf[:start]
        if len(buf) >= 3 and buf[2] == 0xFF:     # FF FF FF: the first FF was noise
            del buf[:1]
            continue
        if len(buf) < 4:
            return out
        length = buf[3]
        if length < 2:
            del buf[:1]
            continue
        total = 4 + length
        if len(buf) < total:
            return out
        pkt = bytes(buf[:total])
        del buf[:total]
        ok = checksum1(pkt[2:-1]) == pkt[-1]
        out.append((pkt[2], pkt[4], pkt[5:-1], ok))


# -- the servos -------------------------------------------------------------------------------

ADDR_MODEL, ADDR_FIRMWARE, ADDR_ID, ADDR_OPMODE = 0, 6, 7, 11
ADDR_VEL_LIMIT, ADDR_MAX_POS, ADDR_MIN_POS = 44, 48, 52
ADDR_TORQUE, ADDR_LED, ADDR_HW_ERROR = 64, 65, 70
ADDR_PROFILE_VEL, ADDR_GOAL_POS, ADDR_MOVING, ADDR_MOVING_STATUS = 112, 116, 122, 123
ADDR_PRESENT_VEL, ADDR_PRESENT_POS, ADDR_TEMPERATURE = 128, 132, 146
VEL_UNIT = 0.229 * 2.0 * math.pi / 60.0     # rad/s per profile/present velocity unit
POS_PER_RAD = 4096.0 / (2.0 * math.pi)


@dataclass
class ServoSim:
    """One X-series servo: control table plus a float position for smooth motion."""

    dxl_id: int
    model: int = 1020
    position: float = 2048.0
    table: bytearray = field(default_factory=lambda: bytearray(1024))

    def __post_init__(self) -> None:
        self.put(ADDR_MODEL, 2, self.model)
        self.put(ADDR_FIRMWARE, 1, 48)
        self.put(ADDR_ID, 1, self.dxl_id)
        self.put(8, 1, 1)                  # baud rate index 1 = 57600
        self.put(ADDR_OPMODE, 1, 3)        # position control
        self.put(24, 4, 10)                # moving threshold
        self.put(ADDR_VEL_LIMIT, 4, 265)
        self.put(ADDR_MAX_POS, 4, 4095)
        self.put(ADDR_MIN_POS, 4, 0)
        self.put(ADDR_GOAL_POS, 4, round(self.position))
        self.put(ADDR_PRESENT_POS, 4, round(self.position))
        self.put(ADDR_TEMPERATURE, 1, 35)
        self.put(144, 2, 120)              # 12.0 V

    def put(self, addr: int, size: int, value: int) -> None:
        self.table[addr:addr + size] = (int(value) & ((1 << 8 * size) - 1)).to_bytes(size, "little")

    def angle(self) -> float:
        return (self.position - 2048.0) / POS_PER_RAD

    def set_hw_error(self, bits: int) -> None:
        self.table[ADDR_HW_ERROR] = bits
        if bits:
            self.table[ADDR_TORQUE] = 0

    def get(self, addr: int, size: int, signed: bool = False) -> int:
        return int.from_bytes(self.table[addr:addr + size], "little", signed=signed)

    def advance(self, dt: float) -> None:
        """Move toward the goal at the profile velocity for dt seconds."""
        torque = self.table[ADDR_TORQUE] == 1
        goal = self.get(ADDR_GOAL_POS, 4, signed=True)
        vel = 0.0
        if torque and dt > 0:
            units = self.get(ADDR_PROFILE_VEL, 4) or self.get(ADDR_VEL_LIMIT, 4)
            step = units * VEL_UNIT * POS_PER_RAD * dt
            diff = goal - self.position
            move = max(-step, min(step, diff))
            self.position += move
            vel = (move / dt) / (VEL_UNIT * POS_PER_RAD)
        moving = torque and abs(goal - self.position) > self.get(24, 4)
        self.put(ADDR_PRESENT_POS, 4, round(self.position))
        self.put(ADDR_PRESENT_VEL, 4, round(vel))
        self.table[ADDR_MOVING] = int(moving)
        self.table[ADDR_MOVING_STATUS] = 0x01 if abs(goal - self.position) <= 10 else 0x02

    def write(self, addr: int, data: bytes) -> int:
        """Apply a WRITE; returns the status error byte (0 = accepted)."""
        if addr + len(data) > len(self.table):
            return ERR_RANGE
        if addr < 64 and self.table[ADDR_TORQUE] == 1:
            return ERR_ACCESS
        hw = self.table[ADDR_HW_ERROR]
        if addr <= ADDR_TORQUE < addr + len(data) and hw and data[ADDR_TORQUE - addr] == 1:
            return ERR_RESULT | ALERT           # in shutdown: torque stays off until reboot
        if addr <= ADDR_GOAL_POS and ADDR_GOAL_POS + 4 <= addr + len(data):
            off = ADDR_GOAL_POS - addr
            goal = int.from_bytes(data[off:off + 4], "little", signed=True)
            lo, hi = self.get(ADDR_MIN_POS, 4, True), self.get(ADDR_MAX_POS, 4, True)
            if not lo <= goal <= hi:
                return ERR_LIMIT
        self.table[addr:addr + len(data)] = data
        return 0


# AX-12 control table (Protocol 1.0); MX servos in Protocol 1.0 use the same addresses.
AX_TORQUE, AX_GOAL, AX_SPEED, AX_PRESENT, AX_MOVING = 24, 30, 32, 36, 46
AX_CW_LIMIT, AX_CCW_LIMIT = 6, 8
AX_POS_PER_RAD = 1023.0 / math.radians(300.0)
AX_VEL_UNIT = 0.111 * 2.0 * math.pi / 60.0   # rad/s per moving-speed unit; 0 = maximum
ERR1_ANGLE, ERR1_CHECKSUM, ERR1_INSTRUCTION = 0x02, 0x10, 0x40


@dataclass
class AxServoSim:
    """One AX-12 servo (Protocol 1.0): 0..1023 over 300°, centre 512."""

    dxl_id: int
    model: int = 12
    position: float = 512.0
    hw_error: int = 0          # Protocol 1.0 status error bits 0 (voltage), 2 (heat), 5 (load)
    table: bytearray = field(default_factory=lambda: bytearray(64))

    def __post_init__(self) -> None:
        self.put(0, 2, self.model)
        self.put(2, 1, 24)                 # firmware
        self.put(3, 1, self.dxl_id)
        self.put(4, 1, 34)                 # 57600 baud
        self.put(AX_CW_LIMIT, 2, 0)
        self.put(AX_CCW_LIMIT, 2, 1023)
        self.put(34, 2, 1023)              # torque limit
        self.put(AX_GOAL, 2, round(self.position))
        self.put(AX_PRESENT, 2, round(self.position))
        self.put(42, 1, 120)               # 12.0 V
        self.put(43, 1, 35)

    put = ServoSim.put
    get = ServoSim.get

    def angle(self) -> float:
        return (self.position - 512.0) / AX_POS_PER_RAD

    def set_hw_error(self, bits: int) -> None:
        self.hw_error = bits
        if bits:
            self.table[AX_TORQUE] = 0

    def advance(self, dt: float) -> None:
        torque = self.table[AX_TORQUE] == 1
        goal = self.get(AX_GOAL, 2)
        if torque and dt > 0:
            units = self.get(AX_SPEED, 2) or 1023
            step = units * AX_VEL_UNIT * AX_POS_PER_RAD * dt
            self.position += max(-step, min(step, goal - self.position))
        self.put(AX_PRESENT, 2, round(self.position))
        self.table[AX_MOVING] = int(torque and abs(goal - self.position) > 1)

    def write(self, addr: int, data: bytes) -> int:
        if addr + len(data) > len(self.table):
            return ERR1_INSTRUCTION
        if addr <= AX_TORQUE < addr + len(data) and self.hw_error and data[AX_TORQUE - addr]:
            return self.hw_error                 # in shutdown until the fault ends
        if addr <= AX_GOAL and AX_GOAL + 2 <= addr + len(data):
            goal = int.from_bytes(data[AX_GOAL - addr:AX_GOAL - addr + 2], "little")
            if not self.get(AX_CW_LIMIT, 2) <= goal <= self.get(AX_CCW_LIMIT, 2):
                return ERR1_ANGLE
        self.table[addr:addr + len(data)] = data
        return 0


class DynamixelBusTwin(TwinControl):
    """Servos on one pty bus; ``start()`` returns the path to give the SDK's PortHandler."""

    _thread_name = "dxl-twin"

    def __init__(self, models: dict[int, int] | None = None, fault_rate: float = 0.0,
                 seed: int = 0, protocol: float = 2.0) -> None:
        super().__init__()
        if protocol not in (1.0, 2.0):
            raise ValueError(f"dynamixel twin: protocol {protocol}: 1.0 or 2.0")
        self.protocol = protocol
        models = models or ({1: 1020, 2: 1060} if protocol == 2.0 else {1: 12, 2: 12})
        self.fault_rate = float(fault_rate)   # probability per sent byte of a flipped byte
        self._rng = random.Random(seed)
        servo_cls = ServoSim if protocol == 2.0 else AxServoSim
        self.servos = {i: servo_cls(i, m) for i, m in models.items()}
        self.fault: str | None = None
        self.fault_ids: set[int] | None = None
        self.delay_s = 0.3
        self.packets_in = 0
        self.path = ""
        self.pty: PtyDevice | None = None
        self._t = time.monotonic()
        self._outbox: list[tuple[float, int, bytes]] = []
        self._n = 0

    # -- control from tests ---------------------------------------------------------------
    def set_fault(self, kind: str | None, ids=None, delay_s: float | None = None) -> None:
        if kind not in (None, "no_reply", "late", "corrupt_crc", "hardware_error"):
            raise ValueError(f"dynamixel twin fault {kind!r}")
        with self._lock:
            if delay_s is not None:
                self.delay_s = float(delay_s)
            self.fault_ids = None if ids is None else set(ids)
            self.fault = kind
            for s in self.servos.values():
                hit = self.fault_ids is None or s.dxl_id in self.fault_ids
                if kind == "hardware_error" and hit:
                    s.set_hw_error(0x04)                # overheating; torque drops
                elif kind is None:
                    s.set_hw_error(0)

    def angle(self, dxl_id: int) -> float:
        """Present angle (rad) of a servo (0 at the centre position)."""
        with self._lock:
            self._advance()
            return self.servos[dxl_id].angle()

    def _advance(self) -> None:
        now = time.monotonic()
        dt, self._t = now - self._t, now
        for s in self.servos.values():
            s.advance(dt)

    def _faulty(self, dxl_id: int, kind: str) -> bool:
        return self.fault == kind and (self.fault_ids is None or dxl_id in self.fault_ids)

    # -- the bus ------------------------------------------------------------------------
    def _reply(self, out: list[tuple[int, bytes]], dxl_id: int, error: int,
               params: bytes = b"") -> None:
        s = self.servos[dxl_id]
        if s.table[ADDR_HW_ERROR]:
            error |= ALERT
        out.append((dxl_id, status_packet(dxl_id, error, params)))

    def handle(self, dxl_id: int, inst: int, params: bytes,
               crc_ok: bool) -> list[tuple[int, bytes]]:
        """Status packets (id, bytes) answering one instruction packet."""
        out: list[tuple[int, bytes]] = []
        self._advance()
        if not crc_ok:
            if dxl_id in self.servos:
                self._reply(out, dxl_id, ERR_CRC)
            return out
        if inst == INST_PING:
            ids = sorted(self.servos) if dxl_id == BROADCAST_ID else [dxl_id]
            for i in ids:
                if i in self.servos:
                    s = self.servos[i]
                    self._reply(out, i, 0, s.model.to_bytes(2, "little") + bytes([48]))
        elif inst == INST_SYNC_READ and dxl_id == BROADCAST_ID and len(params) >= 4:
            addr, n = int.from_bytes(params[0:2], "little"), int.from_bytes(params[2:4], "little")
            for i in params[4:]:
                if i in self.servos:
                    self._reply(out, i, 0, bytes(self.servos[i].table[addr:addr + n]))
        elif inst == INST_SYNC_WRITE and dxl_id == BROADCAST_ID and len(params) >= 4:
            addr, n = int.from_bytes(params[0:2], "little"), int.from_bytes(params[2:4], "little")
            rest = params[4:]
            for k in range(0, len(rest) - n, n + 1):
                i = rest[k]
                if i in self.servos and not self._faulty(i, "no_reply"):
                    self.servos[i].write(addr, rest[k + 1:k + 1 + n])
        elif dxl_id in self.servos:
            s = self.servos[dxl_id]
            if inst == INST_READ and len(params) == 4:
                addr, n = (int.from_bytes(params[0:2], "little"),
                           int.from_bytes(params[2:4], "little"))
                if addr + n > len(s.table):
                    self._reply(out, dxl_id, ERR_RANGE)
                else:
                    self._reply(out, dxl_id, 0, bytes(s.table[addr:addr + n]))
            elif inst == INST_WRITE and len(params) >= 3:
                err = s.write(int.from_bytes(params[0:2], "little"), params[2:])
                self._reply(out, dxl_id, err)
            elif inst == INST_REBOOT:
                s.table[ADDR_HW_ERROR] = 0
                s.table[ADDR_TORQUE] = 0
                if self._faulty(dxl_id, "hardware_error"):
                    self.fault = None
                self._reply(out, dxl_id, 0)
            else:
                self._reply(out, dxl_id, ERR_INSTRUCTION)
        return out

    def handle1(self, dxl_id: int, inst: int, params: bytes,
                ok: bool) -> list[tuple[int, bytes]]:
        """Protocol 1.0: PING, READ, WRITE, SYNC_WRITE (AX-12 table)."""
        out: list[tuple[int, bytes]] = []
        self._advance()

        def reply(i: int, err: int, data: bytes = b"") -> None:
            out.append((i, build_packet1(i, err | self.servos[i].hw_error, data)))

        if dxl_id == BROADCAST_ID and inst == INST_SYNC_WRITE and ok and len(params) >= 2:
            addr, n = params[0], params[1]
            rest = params[2:]
            for k in range(0, len(rest) - n, n + 1):
                i = rest[k]
                if i in self.servos and not self._faulty(i, "no_reply"):
                    self.servos[i].write(addr, rest[k + 1:k + 1 + n])
            return out
        if dxl_id not in self.servos:
            return out
        s = self.servos[dxl_id]
        if not ok:
            reply(dxl_id, ERR1_CHECKSUM)
        elif inst == INST_PING:
            reply(dxl_id, 0)
        elif inst == INST_READ and len(params) == 2:
            addr, n = params
            if addr + n > len(s.table):
                reply(dxl_id, ERR1_INSTRUCTION)
            else:
                reply(dxl_id, 0, bytes(s.table[addr:addr + n]))
        elif inst == INST_WRITE and len(params) >= 2:
            reply(dxl_id, s.write(params[0], params[1:]))
        else:
            reply(dxl_id, ERR1_INSTRUCTION)
        return out

    def _on_packets(self, buf: bytearray) -> None:
        now = time.monotonic()
        p1 = self.protocol == 1.0
        parse, handle = (parse_packets1, self.handle1) if p1 else (parse_packets, self.handle)
        with self._lock:
            for dxl_id, inst, params, ok in parse(buf):
                self.packets_in += 1
                for sid, pkt in handle(dxl_id, inst, params, ok):
                    if self._faulty(sid, "no_reply"):
                        continue
                    due = now
                    if self._faulty(sid, "late"):
                        due = now + self.delay_s
                    if self._faulty(sid, "corrupt_crc"):
                        pkt = pkt[:-1] + bytes([pkt[-1] ^ 0x5A])   # CRC high byte / checksum
                    self._n += 1
                    heapq.heappush(self._outbox, (due, self._n, pkt))

    def _run(self) -> None:
        pty = self.pty
        buf = bytearray()
        while self._running:
            self._serve_requests()
            wait = 0.05      # bounds how long stop() waits for this thread
            if self._outbox:
                wait = min(wait, max(0.0, self._outbox[0][0] - time.monotonic()))
            try:
                data = pty.read(4096, wait)
                if data:
                    buf += data
                    self._on_packets(buf)
                while self._outbox and self._outbox[0][0] <= time.monotonic():
                    _, _, pkt = heapq.heappop(self._outbox)
                    if self.fault_rate > 0:
                        pkt = flip_bytes(pkt, self.fault_rate, self._rng)
                    pty.write(pkt)
            except PtyClosed:
                return

    def start(self) -> str:  # type: ignore[override]  # the path, as serve_until_signal wants
        """Open the bus pty and serve it; returns the path to give the SDK's PortHandler."""
        if not self._running:
            self.pty = PtyDevice()
            self.path = self.pty.path
            self._t = time.monotonic()
            super().start()
        return self.path

    def stop(self) -> None:
        super().stop()
        if self.pty is not None:
            self.pty.close()

    def __enter__(self) -> DynamixelBusTwin:
        self.start()
        return self


def main(args) -> int:
    """``cgamap sim-device dynamixel-pantilt``: servos 1 (XM430-W350) and 2 (XL430-W250)."""
    twin = DynamixelBusTwin(fault_rate=float(getattr(args, "fault_rate", 0.0) or 0.0),
                            seed=int(getattr(args, "seed", 0) or 0))
    return serve_until_signal(twin.start, twin.stop)
