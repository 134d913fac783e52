"""SICK lasers: decode throughput against the wire's own rate.

- LMS2xx: a 361-value (180°/0.5°) ``B0`` telegram, 732 bytes, through the frame parser (CRC),
  the B0 decoder and the scan assembler, fed in whole buffers and in 64-byte serial-sized
  chunks; compared with the rate the wire allows at 500 kbaud (7320 bits a telegram) and the
  sensor's own 37.5 Hz for a full 0.5° scan (two 75 Hz sweeps).
- CoLa A: an 811-value TiM5xx ``LMDscandata`` telegram (DIST1 + RSSI1, ~6 kB), splitter +
  field parser; compared with the TiM5xx's 15 Hz.  CoLa B: the same scan in binary (~2.5 kB).
- End to end: the real LMS driver over a pty against the twin running flat out in this process
  (the twin shares the CPU, so this is a lower bound).
Measured, never asserted.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from cgamap.drivers.cola import (
    ColaAParser,
    ColaBParser,
    parse_scandata,
    parse_scandata_b,
    scan_from_data,
)
from cgamap.drivers.lms2xx import (
    FrameParser,
    Lms2xxDriver,
    ScanAssembler,
    crc16_sick,
    decode_b0,
    frame,
)
from cgamap.drivers.sim.cola import ColaTwin
from cgamap.drivers.sim.lms2xx import Lms2xxTwin

LMS_BAUD = 500000
LMS_SCAN_HZ = 37.5    # 361 values at 0.5°: two 75 Hz sweeps
TIM_HZ = 15.0


def _lms_frames(n: int) -> list[bytes]:
    rng = np.random.default_rng(0)
    out = []
    for _ in range(n):
        vals = rng.integers(30, 8000, 361).astype("<u2")
        payload = b"\xB0" + (361).to_bytes(2, "little") + vals.tobytes() + b"\x10"
        out.append(frame(payload, 0x80))
    return out


def _lms_rate(stream: bytes, chunk: int, frames_in_stream: int, seconds: float) -> float:
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        parser = FrameParser()
        asm = ScanAssembler(180, 0.5, parser.errors)
        for i in range(0, len(stream), chunk):
            for ev in parser.feed(stream[i:i + chunk], 0):
                if asm.add(decode_b0(ev.payload)) is not None:
                    n += 1
    dt = time.perf_counter() - t0
    assert n % frames_in_stream == 0
    return n / dt


def _cola_rate(telegram: bytes, seconds: float) -> float:
    parser = ColaAParser()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for toks in parser.feed(telegram):
            scan_from_data(parse_scandata(toks), 0)
            n += 1
    return n / (time.perf_counter() - t0)


def _cola_b_rate(telegram: bytes, seconds: float) -> float:
    parser = ColaBParser()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for toks in parser.feed(telegram):
            scan_from_data(parse_scandata_b(toks[2]), 0)
            n += 1
    return n / (time.perf_counter() - t0)


def _crc_rate(data: bytes, seconds: float) -> float:
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        crc16_sick(data)
        n += 1
    return n / (time.perf_counter() - t0)


def _lms_end_to_end(seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        twin = Lms2xxTwin("corridor", link=str(Path(tmp) / "tty"), time_scale=50.0)
        twin.start()
        try:
            drv = Lms2xxDriver(twin.path, session_baud=LMS_BAUD, resolution=0.5)
            drv.open()
            n, t0 = 0, time.perf_counter()
            while time.perf_counter() - t0 < seconds:
                if drv.read_scan(1.0) is not None:
                    n += 1
            dt = time.perf_counter() - t0
            drv.close()
        finally:
            twin.stop()
    return {"scans_per_s": round(n / dt, 1), "sent_per_s": round(twin.stats["scans"] / dt, 1),
            "errors": drv.errors.as_dict()}


def run() -> dict:
    frames = _lms_frames(50)
    stream = b"".join(frames)
    wire_hz = LMS_BAUD / (len(frames[0]) * 10)
    whole = _lms_rate(stream, len(stream), 50, 2.0)
    chunked = _lms_rate(stream, 64, 50, 2.0)

    twin = ColaTwin("room")
    tel, _ = twin._scandata("sSN")
    twin.stop()
    cola = _cola_rate(tel, 2.0)
    twin_b = ColaTwin("room", binary=True)
    tel_b, _ = twin_b._scandata("sSN")
    twin_b.stop()
    cola_b = _cola_b_rate(tel_b, 1.0)

    return {
        "lms2xx_361": {
            "telegram_bytes": len(frames[0]),
            "decode_scans_per_s": round(whole, 1),
            "decode_scans_per_s_64B_chunks": round(chunked, 1),
            "wire_limit_500k_per_s": round(wire_hz, 1),
            "sensor_rate_hz": LMS_SCAN_HZ,
            "x_sensor_rate": round(whole / LMS_SCAN_HZ, 1),
            "x_wire_limit_500k": round(whole / wire_hz, 1),
            "x_sensor_rate_64B_chunks": round(chunked / LMS_SCAN_HZ, 1),
            "crc_per_s_732B": round(_crc_rate(frames[0][:-2], 1.0), 1),
        },
        "cola_tim5xx_811": {
            "telegram_bytes": len(tel),
            "decode_scans_per_s": round(cola, 1),
            "sensor_rate_hz": TIM_HZ,
            "x_sensor_rate": round(cola / TIM_HZ, 1),
        },
        "cola_b_tim5xx_811": {
            "telegram_bytes": len(tel_b),
            "decode_scans_per_s": round(cola_b, 1),
            "sensor_rate_hz": TIM_HZ,
            "x_sensor_rate": round(cola_b / TIM_HZ, 1),
        },
        "lms2xx_end_to_end_pty_361": _lms_end_to_end(3.0),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
