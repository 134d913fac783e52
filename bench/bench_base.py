"""Wheel base and pan-tilt head against their twins (real pymodbus client, real dynamixel-sdk):
odometry poll rate reached at the configured 50 Hz and flat out, deadline lateness, the
scripted square's closing error, and pan-tilt command round trips (median, p95).

The twins run in this process (threads), so figures include their share of the CPU; on the
robot the device's own reply latency adds to the round trips."""

from __future__ import annotations

import time

import numpy as np
from cgamap.drivers.modbus_base import ModbusBase, ModbusBaseConfig
from cgamap.drivers.pantilt import PanTilt, PanTiltConfig
from cgamap.drivers.sim.dynamixel import DynamixelBusTwin
from cgamap.drivers.sim.modbus_base import BaseTwinConfig, ModbusBaseTwin, square_script
from cgamap.mapping.odometry import WheelGeometry, integrate_increments, ticks_to_increment


def _stats_ms(samples_s: list[float]) -> dict:
    a = np.asarray(samples_s) * 1e3
    return {"n": int(a.size), "median_ms": round(float(np.median(a)), 3),
            "p95_ms": round(float(np.percentile(a, 95)), 3),
            "max_ms": round(float(a.max()), 3)}


def _flat_out(url: str, seconds: float) -> dict:
    """Back-to-back reads (no pacing): the transaction rate the link and twin allow."""
    with ModbusBase(ModbusBaseConfig(url=url, timeout_s=0.2)) as base:
        t0 = time.monotonic()
        times = []
        while time.monotonic() - t0 < seconds:
            t = time.perf_counter()
            base.read()
            times.append(time.perf_counter() - t)
        errors = base.errors.as_dict()
    return {"reads_per_s": round(len(times) / (time.monotonic() - t0), 1),
            "read_round_trip": _stats_ms(times), "errors": errors}


def _poll_rate(url: str, rate: float, seconds: float) -> dict:
    with ModbusBase(ModbusBaseConfig(url=url, rate_hz=rate, timeout_s=0.2)) as base:
        t0 = time.monotonic()
        stamps = []
        for msg in base.poll():
            stamps.append(msg.stamp_ns)
            if time.monotonic() - t0 >= seconds:
                break
        errors = base.errors.as_dict()
    st = np.asarray(stamps, dtype=np.int64)
    dt = np.diff(st) * 1e-9
    # drift check: with absolute deadlines sample k is due at t0 + k / rate
    late = (st - st[0]) * 1e-9 - np.arange(len(st)) / rate
    return {"configured_hz": rate,
            "reached_hz": round((len(st) - 1) / ((st[-1] - st[0]) * 1e-9), 2),
            "period_std_ms": round(float(dt.std() * 1e3), 3),
            "period_max_ms": round(float(dt.max() * 1e3), 3),
            "deadline_lateness_ms": {"median": round(float(np.median(late) * 1e3), 3),
                                     "p95": round(float(np.percentile(late, 95) * 1e3), 3),
                                     "last": round(float(late[-1] * 1e3), 3)},
            "errors": errors}


def _square(time_scale: float = 5.0) -> dict:
    r, b, tpr = 0.05, 0.30, 4096
    twin = ModbusBaseTwin(BaseTwinConfig(wheel_radius=r, track_width=b, ticks_per_rev=tpr,
                                         time_scale=time_scale))
    twin.start()
    try:
        ticks = []
        with ModbusBase(ModbusBaseConfig(url=twin.url, rate_hz=50.0)) as base:
            end = time.monotonic() + 30.0
            first = base.read()
            ticks.append((first.left, first.right))
            twin.run_script(square_script(1.0, 10.0, r, b, pause=0.3))
            for msg in base.poll():
                ticks.append((msg.left, msg.right))
                if twin.script_done() or time.monotonic() > end:
                    break
            last = base.read()
            if last is not None:
                ticks.append((last.left, last.right))
        t = np.asarray(ticks)
        inc = ticks_to_increment(np.diff(t[:, 0]), np.diff(t[:, 1]), WheelGeometry(r, b, tpr))
        pose = integrate_increments(inc)[-1]
        truth = twin.true_pose()
    finally:
        twin.stop()
    return {"side_m": 1.0, "polls": len(ticks),
            "position_error_m": round(float(np.hypot(pose[0] - truth[0], pose[1] - truth[1])), 5),
            "heading_error_rad": round(float(abs(np.angle(np.exp(1j * (pose[2] - truth[2]))))), 5)}


def _pantilt(n: int = 200) -> dict:
    twin = DynamixelBusTwin()
    path = twin.start()
    try:
        with PanTilt(PanTiltConfig(url=path, profile_velocity=6.0)) as head:
            head.torque(True)
            ping, state, move, reach = [], [], [], []
            for _ in range(n):
                t = time.perf_counter()
                head.ping(1)
                ping.append(time.perf_counter() - t)
                t = time.perf_counter()
                head.read_state()
                state.append(time.perf_counter() - t)
            goals = [(0.3, 0.2), (-0.3, -0.2)] * 5
            for pan, tilt in goals:
                t = time.perf_counter()
                head.move(pan, tilt)
                move.append(time.perf_counter() - t)
                head.wait_until_reached(pan, tilt, tol=0.005, timeout=5.0, period=0.005)
                reach.append(time.perf_counter() - t)
            errors = head.errors.as_dict()
    finally:
        twin.stop()
    return {"ping_round_trip": _stats_ms(ping),
            "state_read_two_sync_reads": _stats_ms(state),
            "move_sync_write": _stats_ms(move),
            "move_0.36rad_to_reached_at_6rad_s": _stats_ms(reach),
            "errors": errors}


def _sdk_pitfalls(n: int = 10) -> dict:
    """CPU spent per reply timeout, and wrong answers after late replies: the unmodified SDK
    (busy-wait receive, 34 ms timeout, no resync) against the driver's workarounds."""
    import dynamixel_sdk as sdk

    twin = DynamixelBusTwin()
    path = twin.start()
    out: dict = {}
    try:
        port = sdk.PortHandler(path)
        port.openPort()
        ph = sdk.PacketHandler(2.0)
        c = time.process_time()
        for _ in range(n):
            ph.ping(port, 9)                           # absent id: a timeout each
        out["raw_sdk_cpu_ms_per_timeout"] = round((time.process_time() - c) / n * 1e3, 2)
        twin.set_fault("late", delay_s=0.05)           # replies after the SDK's ~34 ms
        wrong = 0
        for _ in range(n):
            model, res, _ = ph.ping(port, 1)
            val, res2, _ = ph.read4ByteTxRx(port, 1, 132)
            wrong += int(res == 0 and model != 1020) + int(res2 == 0 and val != 2048)
        twin.set_fault(None)
        time.sleep(0.1)
        port.closePort()
        out["raw_sdk_wrong_answers_with_50ms_late_replies"] = f"{wrong} of {2 * n}"
        with PanTilt(PanTiltConfig(url=path, max_timeouts=10 ** 6)) as head:
            c = time.process_time()
            for _ in range(n):
                head._txrx("ping", lambda: head._ph.ping(head._port, 9), 9)
            out["driver_cpu_ms_per_timeout"] = round((time.process_time() - c) / n * 1e3, 2)
            twin.set_fault("late", delay_s=0.05)
            ok = sum(head.ping(1) == 1020 for _ in range(n))
            out["driver_correct_pings_with_50ms_late_replies"] = f"{ok} of {n}"
    finally:
        twin.stop()
    return out


def run() -> dict:
    out: dict = {}
    for kind in ("tcp", "rtu"):
        twin = ModbusBaseTwin()
        twin.start(rtu=kind == "rtu")
        try:
            out[f"odom_poll_{kind}_50hz"] = _poll_rate(twin.url, 50.0, 3.0)
            out[f"odom_read_{kind}_flat_out"] = _flat_out(twin.url, 2.0)
        finally:
            twin.stop()
    out["odom_square_closing_error"] = _square()
    out["pantilt"] = _pantilt()
    out["dynamixel_sdk_pitfalls"] = _sdk_pitfalls()
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=2))
