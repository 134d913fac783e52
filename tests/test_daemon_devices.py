"""The daemon's device sources against every twin: each model opens, streams and closes
through the supervisor's interface (open / read(timeout) / close)."""

from __future__ import annotations

import time

import pytest
from cgamap.daemon import config as config_mod
from cgamap.daemon.devices import build_source
from cgamap.daemon.twins import start_twin, twin_available
from cgamap.drivers.messages import LaserScan, PanTiltState, WheelTicks

CASES = [  # twin, role, model, message type
    ("lms2xx", "laser", "lms2xx", LaserScan),
    ("hokuyo", "laser", "hokuyo", LaserScan),
    ("cola", "laser", "cola", LaserScan),
    ("modbus-base", "odometry", "modbus-base", WheelTicks),
    ("dynamixel-pantilt", "pantilt", "dynamixel", PanTiltState),
]


@pytest.mark.parametrize("twin,role,model,kind", CASES, ids=[c[0] for c in CASES])
def test_source_streams_from_twin(twin, role, model, kind):
    if not twin_available(twin):
        pytest.skip(f"twin {twin} not in this build")
    t = start_twin(twin)
    try:
        dev = config_mod.validate({"devices": {"d": {"role": role, "model": model,
                                                     "url": t.url, "rate": 20.0}}})["devices"]["d"]
        src = build_source("d", dev)()
        src.open()
        try:
            got = []
            deadline = time.monotonic() + 20
            while len(got) < 3 and time.monotonic() < deadline:
                msg = src.read(1.0)
                if msg is not None:
                    got.append(msg)
            assert len(got) == 3 and all(isinstance(m, kind) for m in got)
            assert [m.stamp_ns for m in got] == sorted(m.stamp_ns for m in got)
        finally:
            src.close()
    finally:
        t.stop()


def test_sim_url_outside_the_demo_fails_clearly():
    dev = config_mod.validate({"devices": {"l": {"role": "laser", "model": "hokuyo",
                                                 "url": "sim://hokuyo"}}})["devices"]["l"]
    src = build_source("l", dev)()
    with pytest.raises(RuntimeError, match="cgamap demo"):
        src.open()
