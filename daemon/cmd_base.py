"""``cgamap odom`` and ``cgamap pantilt``: the wheel base and the pan-tilt head from the shell.

    cgamap odom --device tcp://192.168.0.10:502 [--count N] [--json] [--rate HZ]
    cgamap odom --device /dev/ttyUSB1?baudrate=115200 --wheel-radius 0.075 --track 0.4
    cgamap odom --device 127.0.0.1:5020 --drive 4,6 --count 100    # teleop / the twin
    cgamap pantilt --device /dev/ttyUSB0 [--ids 1,2] status [--json]
    cgamap pantilt --device /dev/ttyUSB0 move 0.5 -0.2 [--no-wait] [--json]
    cgamap pantilt --device /dev/ttyUSB0 torque on|off

``odom`` polls the base's encoders (drivers.modbus_base) and integrates them with
mapping.odometry (exact arcs): each line is the pose since the command started, ``x y theta``
(m, m, rad) with the forward and turn rates; with ``--json`` one object a line with ``seq``,
``stamp_ns``, ``x``, ``y``, ``theta``, ``v``, ``w``, ``left``, ``right``, ``estop``, ``errors``.
``--count 0`` streams until interrupted; a base that stays silent for ``--timeout`` s ends it
with exit code 1.  ``--drive LEFT,RIGHT`` writes wheel-speed set-points (rad/s) for the run and
0,0 at its end: the only way this command moves the base.

``pantilt`` angles are radians (pan about the base z axis, positive left; tilt about the head's
y axis, positive down); ``move`` turns torque on, checks the configured limits before sending
and waits until the goal is reached unless ``--no-wait``; ``status --json`` gives ``pan``,
``tilt``, ``moving``, ``hardware_error`` (per servo), ``models`` and ``errors``.  Exit codes:
0 ok, 1 device absent or not answering, 2 bad input (e.g. a goal outside the limits, refused
before anything is sent), 3 a servo reports a hardware error (``REBOOT`` clears it).
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import time

from cgamap.daemon.cli import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    fmt = argparse.RawDescriptionHelpFormatter
    p = sub.add_parser("odom", help="stream wheel odometry from a Modbus base",
                       description=__doc__, formatter_class=fmt)
    p.add_argument("--device", required=True, metavar="URL",
                   help="tcp://HOST:PORT, rtu+tcp://HOST:PORT, serial://PATH or a device path")
    p.add_argument("--count", type=int, default=0, help="poses to print (0: until stopped)")
    p.add_argument("--json", action="store_true", help="one JSON object per pose and line")
    p.add_argument("--rate", type=float, default=50.0, help="poll rate, Hz")
    p.add_argument("--every", type=int, default=1, help="print every N-th pose")
    p.add_argument("--timeout", type=float, default=5.0,
                   help="give up when the base stays silent this long, s")
    p.add_argument("--unit", type=int, default=None, help="Modbus device id (default 1)")
    p.add_argument("--wheel-radius", type=float, default=0.05, help="m")
    p.add_argument("--track", type=float, default=0.30, help="track width, m")
    p.add_argument("--ticks-per-rev", type=float, default=4096.0, help="encoder ticks per turn")
    p.add_argument("--drive", default=None, metavar="LEFT,RIGHT",
                   help="also command these wheel speeds (rad/s) while streaming, and 0,0 at "
                        "the end (enables the base's set-point writing for this run)")
    p.set_defaults(func=run_odom)

    q = sub.add_parser("pantilt", help="status, move and torque of the Dynamixel pan-tilt head",
                       description=__doc__, formatter_class=fmt)
    q.add_argument("--device", required=True, metavar="URL",
                   help="serial port path, serial://PATH?baudrate=N or socket://HOST:PORT")
    q.add_argument("--ids", default="1,2", metavar="PAN,TILT", help="servo ids (default 1,2)")
    q.add_argument("--json", action="store_true", help="JSON output")
    q.add_argument("--pan-limits", default=None, metavar="MIN,MAX",
                   help="rad; write --pan-limits=-1.5,1.5 when MIN is negative")
    q.add_argument("--tilt-limits", default=None, metavar="MIN,MAX",
                   help="rad; write --tilt-limits=-0.8,0.8 when MIN is negative")
    q.add_argument("--velocity", type=float, default=None, help="profile velocity, rad/s")
    q.add_argument("--protocol", type=float, default=2.0, choices=(1.0, 2.0),
                   help="Dynamixel protocol: 2.0 (X-series, default) or 1.0 (AX, MX)")
    acts = q.add_subparsers(dest="action", metavar="ACTION", required=True)
    hidden_json = {"action": "store_true", "default": argparse.SUPPRESS, "help": "JSON output"}
    a = acts.add_parser("status", help="present angles and hardware error status")
    a.add_argument("--json", **hidden_json)
    m = acts.add_parser("move", help="move to PAN TILT (rad)")
    m.add_argument("pan", type=float)
    m.add_argument("tilt", type=float)
    m.add_argument("--no-wait", action="store_true", help="return once the goal is sent")
    m.add_argument("--wait-timeout", type=float, default=15.0, help="s")
    m.add_argument("--json", **hidden_json)
    t = acts.add_parser("torque", help="torque on or off")
    t.add_argument("state", choices=("on", "off"))
    t.add_argument("--json", **hidden_json)
    q.set_defaults(func=run_pantilt)


# -- odom -------------------------------------------------------------------------------------

def run_odom(args: argparse.Namespace) -> int:
    from cgamap.drivers.modbus_base import ModbusBase, ModbusBaseConfig, ModbusBaseError
    from cgamap.mapping.odometry import OdometryIntegrator, WheelGeometry

    if args.count < 0:
        raise UsageError(f"odom: --count: must be >= 0, got {args.count}")
    if args.every < 1:
        raise UsageError(f"odom: --every: must be >= 1, got {args.every}")
    for flag, value in (("--rate", args.rate), ("--timeout", args.timeout),
                        ("--wheel-radius", args.wheel_radius), ("--track", args.track),
                        ("--ticks-per-rev", args.ticks_per_rev)):
        _positive_finite("odom", flag, value)
    if args.unit is not None and not 1 <= args.unit <= 247:
        raise UsageError(f"odom: --unit: a Modbus unit id is 1..247 (0 is broadcast, no "
                         f"replies), got {args.unit}")
    drive = _pair(args.drive, "--drive", what_cmd="odom") if args.drive else None
    cfg = ModbusBaseConfig(url=args.device, device_id=args.unit, rate_hz=args.rate,
                           wheel_radius=args.wheel_radius, track_width=args.track,
                           ticks_per_rev=args.ticks_per_rev, allow_setpoints=drive is not None)
    if drive is not None and not all(math.isfinite(v) and abs(v) <= cfg.max_wheel_speed
                                     for v in drive):
        raise UsageError(f"odom: --drive: wheel speeds must be finite and within "
                         f"+-{cfg.max_wheel_speed:g} rad/s, got {args.drive}")
    geom = WheelGeometry(cfg.wheel_radius, cfg.track_width, cfg.ticks_per_rev)
    try:
        base = ModbusBase(cfg)
    except ValueError as exc:  # ModbusBaseConfigError (?unit=abc, bad scheme): names the URL
        raise UsageError(f"odom: --device {exc}") from None
    except ModbusBaseError as exc:
        raise UsageError(f"odom: {exc}", 1) from None
    try:
        base.open()            # its error says why (no such device, connection refused, ...)
        if drive is not None and not base.set_wheel_speeds(*drive):
            raise ModbusBaseError("wheel speed set-point not acknowledged")
    except ModbusBaseError as exc:
        raise UsageError(f"odom: {exc}", 1) from None
    odo = OdometryIntegrator(geom)
    printed = 0
    # SIGTERM/SIGHUP (timeout, systemd, a closed terminal) must reach the finally below:
    # with --drive, the default action would leave the wheels turning
    old = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        for k, msg in enumerate(base.poll(max_silence_s=args.timeout)):
            odo.update(msg.left, msg.right, msg.stamp_ns)
            if k % args.every:
                continue
            x, y, th = (float(a) for a in odo.pose)
            v, w = odo.v, odo.w
            if args.json:
                print(json.dumps({"seq": msg.seq, "stamp_ns": msg.stamp_ns, "x": round(x, 6),
                                  "y": round(y, 6), "theta": round(th, 6), "v": round(v, 6),
                                  "w": round(w, 6), "left": msg.left, "right": msg.right,
                                  "estop": msg.estop, "errors": msg.errors}), flush=True)
            else:
                print(f"{msg.stamp_ns * 1e-9:.3f}  x {x:+.4f} m  y {y:+.4f} m  "
                      f"theta {th:+.4f} rad  v {v:+.3f} m/s  w {w:+.3f} rad/s"
                      + ("  E-STOP" if msg.estop else ""), flush=True)
            printed += 1
            if args.count and printed >= args.count:
                break
    except ModbusBaseError as exc:
        raise UsageError(f"odom: {exc}", 1) from None
    finally:
        try:
            if drive is not None:
                base.set_wheel_speeds(0.0, 0.0)   # best effort: leave the base standing
            base.close()
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler)
    return 0


def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _positive_finite(cmd: str, flag: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{cmd}: {flag}: must be a positive number, got {value}")


# -- pantilt ----------------------------------------------------------------------------------

def _pair(text: str, what: str, cast=float, what_cmd: str = "pantilt") -> tuple:
    try:
        a, b = (cast(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"{what_cmd}: {what}: expected two comma-separated values, "
                         f"got {text!r}") from None
    return a, b


def _limits(text: str, what: str) -> tuple[float, float]:
    lo, hi = _pair(text, what)
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise UsageError(f"pantilt: {what}: expected finite MIN < MAX, got {text!r}")
    return lo, hi


def _check_pantilt_args(args: argparse.Namespace) -> tuple[int, int]:
    # the --device URL is checked by PanTilt itself (parse_device_url), before the port opens
    pan_id, tilt_id = _pair(args.ids, "--ids", int)
    for servo_id in (pan_id, tilt_id):
        if not 0 <= servo_id <= 252:  # 253..255 are reserved / broadcast
            raise UsageError(f"pantilt: --ids: a Dynamixel id is 0..252, got {servo_id}")
    if pan_id == tilt_id:
        raise UsageError(f"pantilt: --ids: pan and tilt need two different servos, "
                         f"got {args.ids!r}")
    if args.velocity is not None:  # 0 would mean "no limit" to the servo: not by accident
        _positive_finite("pantilt", "--velocity", args.velocity)
    if args.action == "move":
        if not (math.isfinite(args.pan) and math.isfinite(args.tilt)):
            raise UsageError(f"pantilt move: goal must be finite, got {args.pan} {args.tilt}")
        _positive_finite("pantilt move", "--wait-timeout", args.wait_timeout)
    return pan_id, tilt_id


def run_pantilt(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from cgamap.drivers.pantilt import (
        PanTilt,
        PanTiltConfig,
        PanTiltError,
        PanTiltLimitError,
        describe_hw_error,
    )

    pan_id, tilt_id = _check_pantilt_args(args)
    cfg = PanTiltConfig(url=args.device, protocol=args.protocol).with_ids(pan_id, tilt_id)
    if args.pan_limits:
        lo, hi = _limits(args.pan_limits, "--pan-limits")
        cfg = replace(cfg, pan=replace(cfg.pan, min_rad=lo, max_rad=hi))
    if args.tilt_limits:
        lo, hi = _limits(args.tilt_limits, "--tilt-limits")
        cfg = replace(cfg, tilt=replace(cfg.tilt, min_rad=lo, max_rad=hi))
    if args.velocity is not None:
        cfg = replace(cfg, profile_velocity=args.velocity)
    try:
        head = PanTilt(cfg)
    except PanTiltError as exc:  # a malformed URL (?baudrate=abc, no host:port): names it
        raise UsageError(f"pantilt: --device {exc}") from None
    except ValueError as exc:
        raise UsageError(f"pantilt: --device {args.device}: {exc}") from None
    if args.action == "move":   # refuse a bad goal before even opening the port
        try:
            head.check_goal(args.pan, args.tilt)
        except PanTiltLimitError as exc:
            raise UsageError(f"pantilt move: {exc}") from None
    try:
        head.open()
    except PanTiltError as exc:
        raise UsageError(f"pantilt: {exc}", 1) from None
    except ValueError as exc:  # a malformed URL (unknown scheme, ?baudrate=abc)
        raise UsageError(f"pantilt: --device {args.device}: {exc}") from None
    try:
        if args.action == "torque":
            ok = head.torque(args.state == "on")
            if not ok:
                raise UsageError(f"pantilt torque {args.state}: refused or no reply "
                                 f"(hardware errors: {head.last_hw_error or 'unknown'})", 1)
        elif args.action == "move":
            if not head.torque(True):
                raise UsageError("pantilt move: torque could not be turned on "
                                 "(servo in shutdown? see status)", 1)
            if not head.move(args.pan, args.tilt):
                raise UsageError("pantilt move: goal not sent (no reply)", 1)
            if not args.no_wait:
                if head.wait_until_reached(args.pan, args.tilt, tol=0.005,
                                           timeout=args.wait_timeout) is None:
                    raise UsageError("pantilt move: goal not reached within "
                                     f"{args.wait_timeout} s", 1)
        st = None
        for _ in range(3):
            st = head.read_state()
            if st is not None:
                break
            time.sleep(0.05)
        if st is None:
            raise UsageError("pantilt: no state from the servos", 1)
    except PanTiltError as exc:
        raise UsageError(f"pantilt: {exc}", 1) from None
    finally:
        head.close()
    hw = {"pan": st.hardware_error & 0xFF, "tilt": st.hardware_error >> 8}
    _print_state(args, st, hw, head.models, describe_hw_error)
    return 0 if not st.hardware_error else 3


def _print_state(args, st, hw: dict, models: dict, describe_hw_error) -> None:
    if args.json:
        print(json.dumps({"stamp_ns": st.stamp_ns, "pan": round(st.pan, 6),
                          "tilt": round(st.tilt, 6), "moving": st.moving,
                          "hardware_error": hw,
                          "models": {str(k): v for k, v in models.items()},
                          "errors": st.errors}))
    else:
        print(f"pan {st.pan:+.4f} rad  tilt {st.tilt:+.4f} rad  "
              f"moving {'yes' if st.moving else 'no'}  hardware errors: pan "
              f"{describe_hw_error(hw['pan'])}, tilt {describe_hw_error(hw['tilt'])}")
