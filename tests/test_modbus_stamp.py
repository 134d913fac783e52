"""Wheel-tick stamps of the Modbus base: the midpoint of the tick block's request and reply,
compared with the instants the twin sampled its counters (a twin that holds its answers), and
on a fake clock for maps whose items span two blocks."""

from __future__ import annotations

import statistics
import subprocess
import sys
import textwrap
import time

import pytest
from cgamap.drivers import modbus_base
from cgamap.drivers.messages import WheelTicks
from cgamap.drivers.modbus_base import (
    ModbusBase,
    ModbusBaseConfig,
    ModbusBaseError,
    RegisterField,
    RegisterMap,
    rtu_wire_skew_ns,
)
from cgamap.drivers.sim.modbus_base import BaseTwinConfig, ModbusBaseTwin

DELAY_S = 0.1
MS = 1_000_000


@pytest.fixture(params=["tcp", "rtu", "rtu_over_tcp"])
def slow_twin(request):
    kind = request.param
    tw = ModbusBaseTwin(BaseTwinConfig(response_delay_s=DELAY_S, script=[(100.0, 5.0, 5.0)]))
    tw.start(rtu=kind == "rtu", rtu_over_tcp=kind == "rtu_over_tcp")
    yield tw
    tw.stop()


def test_stamp_lies_within_half_the_round_trip_of_the_sampling(slow_twin):
    n = 6
    stamped: list[tuple[WheelTicks, int]] = []
    with ModbusBase(ModbusBaseConfig(url=slow_twin.url, timeout_s=1.0)) as base:
        slow_twin.samples.clear()
        for _ in range(n):
            msg = base.read()
            assert msg is not None, base.errors
            stamped.append((msg, time.monotonic_ns()))   # the old stamp: after the reply
    samples = list(slow_twin.samples)
    assert len(samples) == n                             # one input-register request per read
    new, old = [], []
    for (msg, after), sampled in zip(stamped, samples, strict=True):
        # causal bounds: the request left before the sample, the reply came after the delay
        assert msg.stamp_uncertainty_ns >= 0.45 * DELAY_S * 1e9
        # within half the round trip (+ 2 ms: the RTU wire-time correction on a pty)
        assert abs(msg.stamp_ns - sampled) <= msg.stamp_uncertainty_ns + 2 * MS
        assert after - sampled >= 0.95 * DELAY_S * 1e9  # the post-reply stamp is a delay late
        new.append(abs(msg.stamp_ns - sampled))
        old.append(after - sampled)
    # typically new ~ delay / 2 and old ~ delay; a loaded box delays replies, so generous
    assert statistics.median(new) < 0.75 * DELAY_S * 1e9 <= statistics.median(old)
    stamps = [m.stamp_ns for m, _ in stamped]
    assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False))


def test_twin_without_delay_samples_every_input_read():
    with ModbusBaseTwin() as tw:
        tw.start()
        with ModbusBase(ModbusBaseConfig(url=tw.url, timeout_s=1.0)) as base:
            msgs = [base.read() for _ in range(3)]
        assert all(m is not None for m in msgs)
        assert len(tw.samples) == 3
        for m, s in zip(msgs, tw.samples, strict=True):
            assert abs(m.stamp_ns - s) <= m.stamp_uncertainty_ns + 2 * MS


# -- blocks on a fake clock ---------------------------------------------------------------------

class FakeTime:
    """The driver's clock: moves only when the fake client works."""

    def __init__(self) -> None:
        self.ns = 10**12

    def monotonic_ns(self) -> int:
        return self.ns

    def monotonic(self) -> float:
        return self.ns * 1e-9

    def sleep(self, seconds: float) -> None:
        self.ns += int(seconds * 1e9)


class TimedClient:
    """Injected client (no trace hook): each request takes ``before`` ns to reach the
    controller and ``after`` ns to come back; logs the instants it sampled at."""

    def __init__(self, clock: FakeTime, before: int, after: int) -> None:
        self.clock, self.before, self.after = clock, before, after
        self.sampled: dict[str, int] = {}

    def connect(self) -> bool:
        return True

    def close(self) -> None:
        pass

    def _read(self, table: str, count: int):
        self.clock.ns += self.before
        self.sampled[table] = self.clock.ns
        self.clock.ns += self.after

        class R:
            registers = [0] * count

            @staticmethod
            def isError() -> bool:
                return False

        return R

    def read_input_registers(self, addr, count, device_id):
        return self._read("input", count)

    def read_holding_registers(self, addr, count, device_id):
        return self._read("holding", count)


@pytest.fixture
def clock(monkeypatch):
    fake = FakeTime()
    monkeypatch.setattr(modbus_base, "time", fake)
    return fake


@pytest.mark.parametrize("tick_table, other_table", [("holding", "input"),
                                                     ("input", "holding")])
def test_stamp_comes_from_the_block_holding_the_ticks(clock, tick_table, other_table):
    regmap = RegisterMap(left_ticks=RegisterField(0, table=tick_table),
                         right_ticks=RegisterField(2, table=tick_table),
                         left_speed=None, right_speed=None,
                         status=RegisterField(8, words=1, signed=False, table=other_table))
    assert len(regmap.read_blocks()) == 2              # holding first, then input
    client = TimedClient(clock, before=5 * MS, after=5 * MS)
    drv = ModbusBase(ModbusBaseConfig(url="tcp://fake:1", registers=regmap),
                     client=client).open()
    msg = drv.read()
    assert msg is not None
    assert msg.stamp_ns == client.sampled[tick_table]  # symmetric trip: exactly the sample
    assert msg.stamp_uncertainty_ns == 5 * MS
    assert clock.ns - msg.stamp_ns >= 5 * MS           # not when the last block came back


def test_asymmetric_trip_stays_within_the_uncertainty(clock):
    client = TimedClient(clock, before=1 * MS, after=40 * MS)
    drv = ModbusBase(ModbusBaseConfig(url="tcp://fake:1"), client=client).open()
    msg = drv.read()
    assert msg is not None
    # sent at 0, sampled at 1 ms, back at 41 ms: stamped at 20.5 ms +- 20.5 ms
    assert msg.stamp_ns - client.sampled["input"] == 19.5 * MS
    assert msg.stamp_uncertainty_ns == 20.5 * MS


def test_rtu_wire_skew():
    # 9 registers: 23-byte reply vs 8-byte request, 10 bits a byte: 15 * 10 / 19200 / 2 s
    assert rtu_wire_skew_ns(9, 19200) == 15 * 10 * 10**9 // (2 * 19200)
    assert rtu_wire_skew_ns(9, 19200) == pytest.approx(3.906 * MS, rel=1e-3)
    assert rtu_wire_skew_ns(2, 115200) < 0.1 * MS


def test_wheel_ticks_json_has_the_uncertainty():
    d = WheelTicks(seq=1, stamp_ns=5, left=1, right=2, stamp_uncertainty_ns=7).to_json()
    assert d["stamp_uncertainty_ns"] == 7 and d["stamp_ns"] == 5 and d["left"] == 1
    assert WheelTicks(seq=1, stamp_ns=5, left=1, right=2).stamp_uncertainty_ns == 0


# -- an answered request that left no window --------------------------------------------------

def _windowless(drv: ModbusBase, client: TimedClient):
    """A ``_request`` that answers (through the client) but sets no stamp window: what a
    broken override or a future path that forgets the window would do."""
    def request(fn, *args, **kw):
        return getattr(client, fn)(*args, device_id=drv.device_id, **kw)
    return request


def test_answer_without_a_window_is_a_driver_error_not_an_assert(clock, monkeypatch):
    client = TimedClient(clock, before=1 * MS, after=1 * MS)
    drv = ModbusBase(ModbusBaseConfig(url="tcp://fake:1"), client=client).open()
    assert drv.read() is not None and drv.last_window_ns is not None   # a good read first
    monkeypatch.setattr(drv, "_request", _windowless(drv, client))
    # the previous read's window is still there: it must not stamp this one
    with pytest.raises(ModbusBaseError, match=r"tcp://fake:1: read_input_registers 0\+9 "
                                               r"answered but left no request/reply window"):
        drv.read()
    monkeypatch.undo()
    assert drv.read() is not None                 # the real path stamps again


def test_answer_without_a_window_raises_under_python_O():
    code = textwrap.dedent("""
        from cgamap.drivers.modbus_base import ModbusBase, ModbusBaseConfig, ModbusBaseError
        class R:
            registers = [0] * 9
            @staticmethod
            def isError():
                return False
        drv = ModbusBase(ModbusBaseConfig(url="tcp://fake:1"), client=object())
        drv._request = lambda *a, **kw: R
        try:
            drv.read()
        except ModbusBaseError as exc:
            print("ModbusBaseError", exc)
    """)
    r = subprocess.run([sys.executable, "-O", "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("ModbusBaseError tcp://fake:1: read_input_registers"), r.stdout


def test_trace_hook_that_never_fires_falls_back_to_the_call(clock):
    """A client that takes the hook but never calls it: stamped around the call, no error."""
    client = TimedClient(clock, before=3 * MS, after=3 * MS)
    drv = ModbusBase(ModbusBaseConfig(url="tcp://fake:1"), client=client).open()
    t0 = clock.ns
    msg = drv.read()
    assert msg is not None and drv.last_window_ns == (t0, clock.ns)
    assert msg.stamp_ns == client.sampled["input"] and msg.stamp_uncertainty_ns == 3 * MS
