"""``cgamap sim-device NAME``: start a simulated twin and print where to connect.

Each twin module provides ``main(args) -> int``: it starts the twin, prints the device path
(pty) or address (host:port) as the first line of stdout (flushed), and serves until SIGINT or
SIGTERM.  The registry below maps the public twin names to those modules.
"""

from __future__ import annotations

import argparse
import importlib

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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    module = importlib.import_module(TWINS[args.name])
    return int(module.main(args) or 0)
