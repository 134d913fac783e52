"""``cgamap sim-device NAME``: start a simulated twin and print where to connect.

Each twin module provides ``main(args) -> int``: it starts the twin, prints the device path
(pty) or address (host:port) as the first line of stdout (flushed), and serves until SIGINT or
SIGTERM.  The registry below maps the public twin names to those modules.
"""

from __future__ import annotations

import argparse
import importlib
import math

from cgamap.daemon.cli import UsageError

TWINS = {
    "lms2xx": "cgamap.drivers.sim.lms2xx",
    "hokuyo": "cgamap.drivers.sim.hokuyo",
    "cola": "cgamap.drivers.sim.cola",
    "modbus-base": "cgamap.drivers.sim.modbus_base",
    "dynamixel-pantilt": "cgamap.drivers.sim.dynamixel",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim-device", help="start a simulated device twin")
    p.add_argument("name", choices=sorted(TWINS), help="which twin")
    p.add_argument("--world", default="corridor", help="simulated world (laser twins)")
    p.add_argument("--fault-rate", type=float, default=0.0,
                   help="probability per byte of a corrupted byte (0 = clean)")
    p.add_argument("--seed", type=int, default=0, help="random seed for noise and faults")
    p.add_argument("--port", type=int, default=0, help="TCP port for network twins (0: any)")
    p.add_argument("--rtu", action="store_true", help="modbus-base: Modbus RTU on a pty")
    p.add_argument("--model", default=None,
                   help="hokuyo: UTM-30LX (default), URG-04LX or UST-10LX (TCP)")
    p.add_argument("--pace-output", action="store_true",
                   help="lms2xx: send bytes at the wire rate of the current baud, in ~2 ms "
                        "chunks, as a real serial line would (default: each telegram at "
                        "once, as a pty delivers it)")
    p.set_defaults(func=run)


LASER_TWINS = ("lms2xx", "hokuyo", "cola")


def _check(args: argparse.Namespace) -> None:
    """Refuse bad flags before a twin starts (its own errors would be tracebacks)."""
    if not (math.isfinite(args.fault_rate) and 0.0 <= args.fault_rate <= 1.0):
        raise UsageError(f"sim-device: --fault-rate: must be a probability in [0, 1], "
                         f"got {args.fault_rate}")
    if not 0 <= args.port <= 65535:
        raise UsageError(f"sim-device: --port: must be a TCP port 0..65535, got {args.port}")
    if args.rtu and args.name != "modbus-base":
        raise UsageError(f"sim-device: --rtu: only for modbus-base, not {args.name}")
    if args.model is not None and args.name != "hokuyo":
        raise UsageError(f"sim-device: --model: only for hokuyo, not {args.name}")
    if getattr(args, "pace_output", False) and args.name != "lms2xx":
        raise UsageError(f"sim-device: --pace-output: only for lms2xx, not {args.name}")
    if args.name in LASER_TWINS:
        from cgamap.drivers.sim.world import WORLDS

        if args.world not in WORLDS:
            raise UsageError(f"sim-device: --world {args.world!r}: unknown world "
                             f"(choose from {', '.join(sorted(WORLDS))})")


def run(args: argparse.Namespace) -> int:
    _check(args)
    module = importlib.import_module(TWINS[args.name])
    try:
        return int(module.main(args) or 0)
    except OSError as exc:  # e.g. the --port is taken
        where = f" --port {args.port}:" if args.port else ""
        raise UsageError(f"sim-device {args.name}:{where} {exc.strerror or exc}", 1) from None
    except (ValueError, RuntimeError) as exc:
        raise UsageError(f"sim-device {args.name}: {exc}", 1) from None
