"""The twins' shared pieces: HokuyoTwin on ScanTwin, DynamixelBusTwin on TwinControl and
PtyDevice (life cycle, no thread or pty left behind)."""

from __future__ import annotations

import os

import pytest
from cgamap.drivers.sim.dynamixel import INST_PING, DynamixelBusTwin, build_packet, parse_packets
from cgamap.drivers.sim.hokuyo import HokuyoTwin
from cgamap.drivers.sim.twin import ScanTwin, TwinControl
from cgamap.drivers.sim.world import NoiseModel
from cgamap.drivers.transport import open_transport


def test_hokuyo_twin_is_a_scan_twin(tmp_path):
    tw = HokuyoTwin("URG-04LX", "room", link=str(tmp_path / "tty"), seed=4, speed=3.0,
                    fault_rate=0.01)
    try:
        assert isinstance(tw, ScanTwin)
        assert tw.speed == tw.time_scale == 3.0 and tw.fault_rate == 0.01
        assert tw.world.name == "room" and tw.noise == NoiseModel(sigma=0.01, dropout=0.01)
        assert len(tw.sent) == 0 and tw.sent.maxlen
        quiet = NoiseModel(0.0)
        assert HokuyoTwin(link=str(tmp_path / "tty2"), noise=quiet).noise is quiet
    finally:
        tw.close()
    with pytest.raises(ValueError, match="unknown Hokuyo model"):
        HokuyoTwin("XYZ-1")


def _ping(path: str) -> bytes:
    with open_transport(path, 1.0) as t:
        t.write(build_packet(1, INST_PING))
        got = bytearray()
        for _ in range(20):
            got += t.read(64, 0.1)
            if parse_packets(bytearray(got)):
                break
        return bytes(got)


def test_dynamixel_twin_life_cycle():
    tw = DynamixelBusTwin()
    assert isinstance(tw, TwinControl)
    path = tw.start()
    try:
        assert tw.start() == path                 # a second start() serves the same bus
        assert os.path.exists(path)
        (dxl_id, _inst, params, ok), = parse_packets(bytearray(_ping(path)))
        # a status packet's params: error byte, then the model number
        assert (dxl_id, ok) == (1, True) and int.from_bytes(params[1:3], "little") == 1020
    finally:
        tw.stop()
    assert not tw._thread.is_alive() and not tw.pty.is_open
    with DynamixelBusTwin(protocol=1.0) as tw1:    # the context manager starts it too
        assert tw1.path and tw1._thread.is_alive()
    assert not tw1._thread.is_alive()
