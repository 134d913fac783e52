"""Hokuyo SCIP 2.0: decode throughput of a 1081-step UTM-30LX ``MD`` scan reply (3372 bytes)
against the sensor's own 40 Hz, with and without conversion to a LaserScan, fed whole and in
serial-sized chunks; and the rate the real driver reaches over a pty against the twin running
flat out (twin in this process, so it shares the CPU).  Measured, never asserted."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np
from cgamap.drivers.hokuyo import HokuyoDriver, scan_to_message
from cgamap.drivers.scip import ScipParser, SensorInfo
from cgamap.drivers.sim.hokuyo import MODELS, HokuyoTwin, scan_reply

WIRE_HZ = 40.0   # UTM-30LX: 2400 rpm, one scan per turn


def _utm_info() -> SensorInfo:
    p = MODELS["UTM-30LX"]
    return SensorInfo("UTM-30LX", p["dmin"], p["dmax"], p["ares"], p["amin"], p["amax"],
                      p["afrt"], p["scan"])


def _decode_rate(blocks: list[bytes], chunk: int | None, convert: bool, seconds: float) -> float:
    info = _utm_info()
    parser = ScipParser()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        for block in blocks:
            pieces = [block] if chunk is None else [block[i:i + chunk]
                                                    for i in range(0, len(block), chunk)]
            for piece in pieces:
                for item in parser.feed(piece, 0):
                    if convert:
                        scan_to_message(item, info)
                    n += 1
    return n / (time.perf_counter() - t0)


def _driver_rate(seconds: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp, \
            HokuyoTwin(link=str(Path(tmp) / "tty"), speed=100.0) as tw, \
            HokuyoDriver(tw.path, 0.5, command_timeout=1.0, stall_timeout=2.0) as d:
        d.read_scan(2.0)
        n, t0 = 0, time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            if d.read_scan(1.0) is not None:
                n += 1
        rate = n / (time.perf_counter() - t0)
        return {"scans_per_s": round(rate, 1), "x_wire_rate": round(rate / WIRE_HZ, 1),
                "twin_sent": len(tw.sent), "errors": d.errors.as_dict()}


def run() -> dict:
    rng = np.random.default_rng(0)
    blocks = [scan_reply("MD0000108001000", "99", 1000 + 25 * i,
                         rng.integers(23, 30000, 1081).astype(np.uint32), "D")
              for i in range(40)]
    out: dict = {"scan_bytes": len(blocks[0]), "steps": 1081, "wire_hz": WIRE_HZ}
    for name, chunk, convert in (("parse_whole", None, False), ("parse_to_laserscan", None, True),
                                 ("parse_to_laserscan_chunks_512", 512, True)):
        rate = _decode_rate(blocks, chunk, convert, 2.0)
        out[name] = {"scans_per_s": round(rate, 1), "x_wire_rate": round(rate / WIRE_HZ, 1)}
    out["driver_over_pty_twin_flat_out"] = _driver_rate(4.0)
    return out


if __name__ == "__main__":
    import json
    print(json.dumps(run(), indent=2))
