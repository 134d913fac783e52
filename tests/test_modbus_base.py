"""Modbus differential base: register coding, encoder wrap, and the real pymodbus client
against the twin (TCP and RTU over a pty): scripted drives, faults, set-point guard."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from cgamap.drivers.modbus_base import (
    ModbusBase,
    ModbusBaseConfig,
    ModbusBaseError,
    RegisterField,
    RegisterMap,
    decode_registers,
    encode_registers,
    unwrap_delta,
)
from cgamap.drivers.sim.modbus_base import (
    BaseTwinConfig,
    ModbusBaseTwin,
    circle_script,
    square_script,
)
from cgamap.mapping.odometry import WheelGeometry, integrate_increments, ticks_to_increment
from hypothesis import given, settings
from hypothesis import strategies as st

R, B, TPR = 0.05, 0.30, 4096


# -- register coding ------------------------------------------------------------------------

def test_word_order_big_and_little():
    assert decode_registers([0x0001, 0x0002], signed=False, word_order="big") == 0x00010002
    assert decode_registers([0x0001, 0x0002], signed=False, word_order="little") == 0x00020001
    assert decode_registers([0xFFFF, 0xFFFE], signed=True, word_order="big") == -2
    assert decode_registers([0xFFFE, 0xFFFF], signed=True, word_order="little") == -2
    assert decode_registers([0x8000], signed=True) == -32768
    assert decode_registers([0x8000], signed=False) == 32768
    assert encode_registers(-2, 2, "big") == [0xFFFF, 0xFFFE]
    assert encode_registers(-2, 2, "little") == [0xFFFE, 0xFFFF]
    assert encode_registers(0x12345678, 2, "big") == [0x1234, 0x5678]


@settings(deadline=None)  # no wall-clock limit on a loaded CI box
@given(st.integers(-(2**31), 2**31 - 1), st.sampled_from(["big", "little"]))
def test_word_order_round_trip(v, order):
    assert decode_registers(encode_registers(v, 2, order), True, order) == v


def test_pymodbus_agrees_on_big_word_order():
    from pymodbus.client import ModbusTcpClient

    regs = ModbusTcpClient.convert_to_registers([-123456], ModbusTcpClient.DATATYPE.INT32)
    assert list(regs) == encode_registers(-123456, 2, "big")


@pytest.mark.parametrize("bits", [16, 32])
def test_encoder_wrap_unwrap(bits):
    m = 1 << bits
    assert unwrap_delta(5, m - 5, bits) == 10          # forward across the wrap
    assert unwrap_delta(m - 5, 5, bits) == -10         # backward across it
    assert unwrap_delta(100, 40, bits) == 60
    # as signed registers: +max -> -max is a step of +1
    assert unwrap_delta(-(m // 2), m // 2 - 1, bits) == 1


@settings(deadline=None)  # no wall-clock limit on a loaded CI box
@given(st.lists(st.integers(-20000, 20000), min_size=1, max_size=50), st.integers(0, 65535))
def test_unwrap_recovers_a_16bit_counter(steps, start):
    true = start + np.cumsum(steps)
    raw = [int(v) % 65536 for v in [start, *true]]
    total = sum(unwrap_delta(raw[i + 1], raw[i], 16) for i in range(len(steps)))
    assert total == int(true[-1] - start)


def test_register_map_blocks_and_config():
    m = RegisterMap()
    assert m.read_blocks() == [("input", 0, 9)]
    m2 = RegisterMap.from_dict({"status": None, "right_ticks": {"address": 10, "words": 1}})
    assert m2.read_blocks() == [("input", 0, 11)]
    with pytest.raises(ValueError, match="unknown"):
        RegisterMap.from_dict({"left_tics": {"address": 0}})
    with pytest.raises(ValueError, match="word_order"):
        RegisterField(0, word_order="middle")
    cfg = ModbusBaseConfig.from_dict({"url": "tcp://h:1", "rate": 20.0,
                                      "params": {"wheel_radius": 0.075, "track": 0.4}})
    assert (cfg.rate_hz, cfg.wheel_radius, cfg.track_width) == (20.0, 0.075, 0.4)
    assert not cfg.allow_setpoints


def test_url_options():
    b = ModbusBase(ModbusBaseConfig(url="tcp://10.0.0.2:502?unit=7"))
    assert b.device_id == 7
    b = ModbusBase(ModbusBaseConfig(url="serial:///dev/ttyUSB0?baudrate=57600"))
    assert b.baudrate == 57600
    b = ModbusBase(ModbusBaseConfig(url="127.0.0.1:5020"))
    assert (b._kind, b._where, b._port) == ("tcp", "127.0.0.1", 5020)
    b = ModbusBase(ModbusBaseConfig(url="/dev/pts/7"))
    assert (b._kind, b._where) == ("rtu", "/dev/pts/7")
    with pytest.raises(ModbusBaseError, match="unsupported scheme"):
        ModbusBase(ModbusBaseConfig(url="http://x"))


class FakeClient:
    """Injected client: serves a list of register blocks in turn."""

    def __init__(self, blocks):
        self.blocks = list(blocks)

    def connect(self):
        return True

    def close(self):
        pass

    def read_input_registers(self, addr, count, device_id):
        regs = self.blocks.pop(0)

        class R:
            registers = regs

            @staticmethod
            def isError():
                return False

        return R


def test_driver_unwraps_16bit_little_endian_map_from_fake_client():
    regmap = RegisterMap(left_ticks=RegisterField(0, words=1, signed=False),
                         right_ticks=RegisterField(1, words=2, word_order="little"),
                         left_speed=None, right_speed=None, status=RegisterField(3, words=1),
                         estop_bit=2)
    blocks = [[65530, *encode_registers(-3, 2, "little"), 0],
              [4, *encode_registers(7, 2, "little"), 4]]
    drv = ModbusBase(ModbusBaseConfig(url="tcp://fake:1", registers=regmap),
                     client=FakeClient(blocks)).open()
    a, b = drv.read(), drv.read()
    assert (a.left, a.right, a.estop) == (65530, -3, False)
    assert (b.left - a.left, b.right - a.right, b.estop) == (10, 10, True)


# -- against the twin -----------------------------------------------------------------------

@pytest.fixture
def twin_factory():
    twins = []

    def make(rtu=False, rtu_over_tcp=False, **kw):
        tw = ModbusBaseTwin(BaseTwinConfig(wheel_radius=R, track_width=B, ticks_per_rev=TPR, **kw))
        tw.start(rtu=rtu, rtu_over_tcp=rtu_over_tcp)
        twins.append(tw)
        return tw

    yield make
    for tw in twins:
        tw.stop()


def drive(twin, script, rate=50.0, limit_s=30.0, **cfg):
    """Read once, start the twin's script, poll until it ends; returns the odometry pose and
    the messages."""
    geom = WheelGeometry(R, B, TPR)
    msgs = []
    end = time.monotonic() + limit_s
    with ModbusBase(ModbusBaseConfig(url=twin.url, rate_hz=rate, timeout_s=0.2, **cfg)) as base:
        first = None
        while first is None and time.monotonic() < end:
            first = base.read()
        msgs.append(first)
        twin.run_script(script)
        for msg in base.poll():
            msgs.append(msg)
            if twin.script_done() or time.monotonic() > end:
                break
        msgs.append(base.read())
    ticks = np.array([(m.left, m.right) for m in msgs if m is not None])
    inc = ticks_to_increment(np.diff(ticks[:, 0]), np.diff(ticks[:, 1]), geom)
    return integrate_increments(inc)[-1], msgs


def close_pose(a, b, pos_tol, ang_tol):
    assert np.hypot(a[0] - b[0], a[1] - b[1]) < pos_tol, (a, b)
    assert abs(math.remainder(a[2] - b[2], 2 * math.pi)) < ang_tol, (a, b)


def test_square_drive_over_tcp_with_wrap(twin_factory):
    pause, scale = 0.3, 5.0
    script = square_script(1.0, 10.0, R, B, pause=pause)
    tw = twin_factory(time_scale=scale, encoder_offset=2**31 - 3000)
    pose, msgs = drive(tw, script)
    truth = tw.true_pose()
    close_pose(truth, (0.0, 0.0, 0.0), 1e-9, 1e-9)         # the square closes exactly
    # Arcs are exact while each poll sees one constant wheel-speed pair (or a pair and a
    # stop); a poll interval longer than a pause (a loaded box) spans a leg and a turn, and
    # the single arc then misplaces up to ~ v * w * gap^2 / 2 (v = 0.5 m/s, w = 3.3 rad/s).
    st = np.array([m.stamp_ns for m in msgs if m is not None])
    gap = float(np.diff(st).max()) * 1e-9 * scale
    tol = 0.01 if gap < pause else 0.01 + 0.5 * 0.5 * 3.34 * gap**2
    close_pose(pose, truth, tol, 0.02)
    assert min(m.left for m in msgs) < 2**31 < max(m.left for m in msgs)  # crossed the wrap
    assert msgs[-1].errors["timeout"] == 0


def test_circle_drive_over_rtu_pty(twin_factory):
    script = circle_script(0.8, 0.6, R, B, turns=0.75)
    tw = twin_factory(rtu=True, time_scale=4.0)
    pose, _ = drive(tw, script)
    truth = tw.true_pose()
    close_pose(truth, (-0.8, 0.8, -math.pi / 2), 1e-6, 1e-6)  # three quarters, centre (0, 0.8)
    close_pose(pose, truth, 0.01, 0.01)                  # constant speeds: arcs are exact


def test_slip_and_bias_show_as_odometry_error(twin_factory):
    # a straight 1 m drive; the left encoder over-reads 2 %: odometry turns right
    tw = twin_factory(time_scale=5.0, bias=(0.02, 0.0))
    pose, _ = drive(tw, [(2.0, 10.0, 10.0)])
    truth = tw.true_pose()
    close_pose(truth, (1.0, 0.0, 0.0), 1e-9, 1e-9)
    assert pose[2] == pytest.approx(-0.02 / B, rel=0.05)   # (sr - sl) / b, 1 m each


@pytest.mark.parametrize("rtu", [False, True, "over_tcp"])
def test_faults_are_counted_and_recovered(twin_factory, rtu):
    tw = twin_factory(rtu=rtu is True, rtu_over_tcp=rtu == "over_tcp")
    with ModbusBase(ModbusBaseConfig(url=tw.url, timeout_s=0.25)) as base:
        assert base.read() is not None
        for fault, counter in (("no_reply", "timeout"), ("slow", "timeout"),
                               ("exception", "device")):
            tw.set_fault(fault, delay_s=0.35)    # later than the timeout, within the drain
            before = base.errors.as_dict()[counter]
            t0 = time.monotonic()
            assert base.read() is None
            assert time.monotonic() - t0 < 5.0   # bounded by the timeout: no stall
            assert base.errors.as_dict()[counter] == before + 1
            tw.set_fault(None)
            # recovery: good reads again (a loaded box may still lose one to a timeout)
            ok = [m for m in (base.read() for _ in range(5)) if m is not None]
            assert len(ok) >= 3, (fault, base.errors)
            assert ok[-1].left == 0 and ok[-1].status == 0
        assert base.errors.disconnects == 0


def test_poll_keeps_its_deadlines_through_a_fault(twin_factory):
    tw = twin_factory()
    tw.set_fault("no_reply")
    with ModbusBase(ModbusBaseConfig(url=tw.url, timeout_s=0.05, rate_hz=50)) as base:
        import threading

        stop = threading.Event()
        threading.Timer(0.6, stop.set).start()
        threading.Timer(0.3, tw.set_fault, args=(None,)).start()
        got = list(base.poll(stop=stop))
    assert base.errors.timeout >= 1
    assert len(got) >= 1                      # recovered once the fault ended


def test_setpoints_refused_unless_enabled(twin_factory):
    tw = twin_factory()
    with ModbusBase(ModbusBaseConfig(url=tw.url)) as base:
        n = tw.requests
        with pytest.raises(ModbusBaseError, match="disabled"):
            base.set_wheel_speeds(1.0, 1.0)
        assert tw.requests == n                      # nothing was sent
    with ModbusBase(ModbusBaseConfig(url=tw.url, allow_setpoints=True)) as base:
        with pytest.raises(ModbusBaseError, match="beyond"):
            base.set_wheel_speeds(100.0, 1.0)
        assert base.set_wheel_speeds(2.0, -1.5)
        msg = base.read()
        assert (msg.left_speed, msg.right_speed) == pytest.approx((2.0, -1.5))
        tw.set_estop(True)
        assert base.read().estop


def test_word_order_matters_on_the_wire(twin_factory):
    little = RegisterMap(left_ticks=RegisterField(0, word_order="little"),
                         right_ticks=RegisterField(2, word_order="little"))
    tw = twin_factory(registers=little, encoder_offset=70000)
    with ModbusBase(ModbusBaseConfig(url=tw.url, registers=little)) as base:
        assert base.read().left == 70000
    with ModbusBase(ModbusBaseConfig(url=tw.url)) as base:
        assert base.read().left == decode_registers(encode_registers(70000, 2, "little"))


# -- CLI --------------------------------------------------------------------------------------

def test_cli_odom_json_lines(twin_factory, capsys, cli_main):
    import json

    tw = twin_factory(script=[(100.0, 4.0, 4.0)], time_scale=2.0)
    rc = cli_main(["odom", "--device", tw.url, "--count", "5", "--json", "--rate", "25",
               "--wheel-radius", str(R), "--track", str(B), "--ticks-per-rev", str(TPR)])
    assert rc == 0
    lines = [json.loads(s) for s in capsys.readouterr().out.splitlines()]
    assert len(lines) == 5
    assert {"stamp_ns", "x", "y", "theta"} <= set(lines[0])
    assert lines[-1]["x"] > lines[0]["x"] and abs(lines[-1]["theta"]) < 1e-9
    assert all(b["stamp_ns"] > a["stamp_ns"] for a, b in zip(lines, lines[1:], strict=False))


def test_cli_odom_errors_are_one_line(twin_factory, capsys, cli_main):
    assert cli_main(["odom", "--device", "http://nowhere", "--count", "1"]) == 2  # usage
    err = capsys.readouterr().err
    assert err.startswith("cgamap: odom:") and err.count("\n") == 1
    tw = twin_factory()
    tw.set_fault("no_reply")
    assert cli_main(["odom", "--device", tw.url, "--count", "1", "--timeout", "0.5"]) == 1
    assert "no reply for 0.5 s" in capsys.readouterr().err


def test_sim_device_process_prints_address_and_stops():
    import os
    import signal
    import subprocess
    import sys

    code = ("import sys; from cgamap.daemon import cli; "
            "cli.COMMAND_MODULES = ['cgamap.daemon.cmd_sim']; "
            "sys.exit(cli.main(['sim-device', 'modbus-base']))")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        line = proc.stdout.readline().strip()
        host, port = line.split(":")
        assert host == "127.0.0.1" and int(port) > 0
        with ModbusBase(ModbusBaseConfig(url=f"tcp://{line}")) as base:
            assert base.read() is not None
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0


@pytest.mark.parametrize("rtu", [False, True])
def test_vanished_device_is_counted_not_hung(rtu):
    tw = ModbusBaseTwin()
    tw.start(rtu=rtu)
    base = ModbusBase(ModbusBaseConfig(url=tw.url, timeout_s=0.1)).open()
    try:
        assert base.read() is not None
        tw.stop()
        assert [base.read() for _ in range(3)] == [None] * 3
        assert base.errors.disconnects == 1 and base.errors.dropped == 2   # backing off
        with pytest.raises(ModbusBaseError, match="no reply for 0.3 s"):
            list(base.poll(max_silence_s=0.3))
    finally:
        base.close()
        tw.stop()


def test_rtu_line_noise_is_counted_and_survived():
    tw = ModbusBaseTwin(BaseTwinConfig(encoder_offset=12345), fault_rate=0.01, seed=3)
    tw.start(rtu=True)
    try:
        with ModbusBase(ModbusBaseConfig(url=tw.url, timeout_s=0.05)) as base:
            got = [base.read() for _ in range(40)]
            ok = [m for m in got if m is not None]
            assert ok and len(ok) < 40 and base.errors.timeout > 0
            assert all(m.left == 12345 for m in ok)        # a CRC-checked frame or nothing
    finally:
        tw.stop()


def test_16bit_unsigned_encoders_wrap_on_the_wire(twin_factory):
    regs = RegisterMap(left_ticks=RegisterField(0, words=1, signed=False),
                       right_ticks=RegisterField(1, words=1, signed=False),
                       left_speed=None, right_speed=None, status=None)
    tw = twin_factory(registers=regs, encoder_offset=65000, time_scale=5.0)
    pose, msgs = drive(tw, [(2.0, 10.0, 10.0)], registers=regs)   # 1 m: 13038 ticks
    raw = [m.left % 65536 for m in msgs if m is not None]
    assert max(raw) > 60000 and min(raw) < 10000                   # the register wrapped
    close_pose(pose, (1.0, 0.0, 0.0), 1e-3, 1e-9)


def test_cli_odom_drive_moves_the_twin_and_stops_it(twin_factory, capsys, cli_main):
    import json

    tw = twin_factory(time_scale=2.0)
    assert cli_main(["odom", "--device", tw.address, "--drive", "5,-5", "--count", "10",
                     "--json", "--wheel-radius", str(R), "--track", str(B)]) == 0
    last = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert last["theta"] < -0.05 and abs(last["x"]) < 1e-6     # turning in place, clockwise
    assert tw._cmd == [0.0, 0.0]                                # stopped at the end
    assert cli_main(["odom", "--device", tw.address, "--drive", "5"]) == 2


@pytest.mark.parametrize("url, needle", [
    ("tcp://127.0.0.1:1?unit=abc", "unit id 'abc' is not a whole number"),
    ("tcp://127.0.0.1:1?unit=0", "1..247"),
    ("tcp://127.0.0.1:1?unit=250", "1..247"),
    ("/dev/ttyX?baudrate=fast", "baud rate 'fast'"),
    ("/dev/ttyX?baud=0", "must be positive"),
    ("tcp://127.0.0.1:http", "host:port"),
])
def test_bad_url_options_are_config_errors(url, needle):
    from cgamap.drivers.modbus_base import ModbusBaseConfigError

    with pytest.raises(ModbusBaseConfigError, match=needle) as ei:
        ModbusBase(ModbusBaseConfig(url=url))
    assert isinstance(ei.value, ModbusBaseError) and url.split("?")[0] in str(ei.value)


def test_open_says_why_it_cannot_connect(tmp_path):
    import socket

    with socket.socket() as s:          # a port nobody listens on (bound, never listening)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(ModbusBaseError, match="cannot connect .*refused"):
            ModbusBase(ModbusBaseConfig(url=f"tcp://127.0.0.1:{port}", timeout_s=0.3)).open()
    with pytest.raises(ModbusBaseError, match="no such device"):
        ModbusBase(ModbusBaseConfig(url=str(tmp_path / "ttyNOPE"))).open()


def test_a_base_that_never_answered_logs_no_warning(caplog):
    """QA: the CLI printed a WARNING line, then its own error line, for one problem."""
    import socket

    with socket.socket() as srv:        # accepts, never replies
        srv.bind(("127.0.0.1", 0))
        srv.listen()
        base = ModbusBase(ModbusBaseConfig(url=f"tcp://127.0.0.1:{srv.getsockname()[1]}",
                                           timeout_s=0.1, rate_hz=50.0))
        with caplog.at_level("DEBUG", logger="cgamap.drivers.modbus_base"), base:
            with pytest.raises(ModbusBaseError, match="no reply"):
                for _ in base.poll(max_silence_s=0.3):
                    pass
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
