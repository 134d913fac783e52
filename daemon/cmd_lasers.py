"""``cgamap scan``: read scans from a laser range finder (or its simulated twin) and print them.

    cgamap scan --device /dev/ttyUSB0 --model lms2xx [--baud 500000] [--count N] [--json]
    cgamap scan --device tcp://192.168.0.1:2111 --model cola --json
    cgamap scan --device "$(cgamap sim-device lms2xx & ...)" --model lms2xx

``--device`` takes a transport URL: a device path, ``serial://PATH?baud=N``, ``tcp://HOST:PORT``,
with ``spy+`` in front (or ``?trace=1``) to hex-dump the traffic (shown with ``-v``).  With
``--json`` each scan is one JSON object a line (``seq``, ``stamp_ns``, ``angle_min``,
``angle_increment``, ``ranges`` in metres with null for no return, ...); otherwise a one-line
summary per scan.  ``--count 0`` reads until interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np
from cgamap.daemon.cli import UsageError

MODELS = {
    "lms2xx": ("cgamap.drivers.lms2xx", "Lms2xxDriver"),
    "hokuyo": ("cgamap.drivers.hokuyo", "HokuyoDriver"),
    "cola": ("cgamap.drivers.cola", "ColaDriver"),
}


def register(subparsers) -> None:
    p = subparsers.add_parser("scan", help="read and print laser scans",
                              description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", required=True, metavar="URL",
                   help="device path or URL (serial://, tcp://, spy+...)")
    p.add_argument("--model", required=True, choices=sorted(MODELS), help="laser protocol")
    p.add_argument("--count", type=int, default=10, help="scans to print (0: until stopped)")
    p.add_argument("--json", action="store_true", help="one JSON object per scan and line")
    p.add_argument("--timeout", type=float, default=5.0,
                   help="give up when no scan arrives for this long, s")
    p.add_argument("--baud", type=int, default=None,
                   help="lms2xx: session baud (9600, 19200, 38400, 500000)")
    p.add_argument("--resolution", type=float, default=None,
                   help="lms2xx: angular resolution in degrees (1, 0.5, 0.25)")
    p.add_argument("--angle", type=int, default=None, help="lms2xx: field of view (180, 100)")
    p.add_argument("--units", choices=("cm", "mm"), default=None, help="lms2xx: range units")
    p.add_argument("--cola", choices=("auto", "A", "B"), default=None,
                   help="cola: ASCII (A) or binary (B) telegrams (auto: B on port 2112)")
    p.set_defaults(func=run)


def _driver(args: argparse.Namespace):
    import importlib

    module_name, cls_name = MODELS[args.model]
    try:
        cls = getattr(importlib.import_module(module_name), cls_name)
    except (ImportError, AttributeError) as exc:
        raise UsageError(f"--model {args.model}: driver not available ({exc})", 1) from None
    kw: dict = {}
    if args.model == "lms2xx":
        if args.baud is not None:
            kw["session_baud"] = args.baud
        if args.resolution is not None:
            kw["resolution"] = args.resolution
        if args.angle is not None:
            kw["angle"] = args.angle
        if args.units is not None:
            kw["units"] = args.units
    elif any(v is not None for v in (args.baud, args.resolution, args.angle, args.units)):
        raise UsageError(f"--baud/--resolution/--angle/--units: only for lms2xx, not {args.model}")
    if args.model == "cola" and args.cola is not None:
        kw["protocol"] = args.cola
    elif args.cola is not None:
        raise UsageError(f"--cola: only for the cola model, not {args.model}")
    try:
        return cls(args.device, reconnect=True, stall_timeout=min(2.0, args.timeout), **kw)
    except ValueError as exc:
        raise UsageError(f"--device {args.device}: {args.model}: {exc}") from None


def summary(scan) -> str:
    r = scan.ranges
    ok = np.isfinite(r)
    rng = (f"{np.nanmin(r):.2f}/{np.nanmedian(r):.2f}/{np.nanmax(r):.2f} m"
           if ok.any() else "no returns")
    return (f"seq {scan.seq} stamp {scan.stamp_ns} beams {len(r)} valid {int(ok.sum())} "
            f"min/median/max {rng} fov {np.degrees(scan.angle_increment * (len(r) - 1)):.1f} deg")


def run(args: argparse.Namespace) -> int:
    if args.count < 0:
        raise UsageError(f"--count: must be >= 0, got {args.count}")
    if not (args.timeout > 0 and math.isfinite(args.timeout)):
        raise UsageError(f"--timeout: must be a positive number of seconds, got {args.timeout}")
    if not args.device.strip():
        raise UsageError("--device: empty (give a device path, serial://PATH or tcp://HOST:PORT)")
    from cgamap.drivers.laser import DeviceError
    from cgamap.drivers.transport import TransportError

    drv = _driver(args)
    try:
        drv.open()
    except (TransportError, DeviceError) as exc:
        raise UsageError(f"--device {args.device}: {exc}", 1) from None
    except ValueError as exc:  # a malformed URL the transport only notices when opening
        raise UsageError(f"--device {args.device}: {exc}") from None
    n = 0
    try:
        while args.count == 0 or n < args.count:
            scan = drv.read_scan(args.timeout)
            if scan is None:
                print(f"cgamap: --device {args.device}: no scan for {args.timeout:g} s "
                      f"(errors: {drv.errors.as_dict()})", file=sys.stderr)
                return 1
            line = json.dumps(scan.to_json()) if args.json else summary(scan)
            print(line, flush=True)
            n += 1
    except (TransportError, DeviceError) as exc:
        raise UsageError(f"--device {args.device}: {exc}", 1) from None
    finally:
        drv.close()
    return 0
