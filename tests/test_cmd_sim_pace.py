"""``cgamap sim-device lms2xx --pace-output``: the flag reaches the twin through the CLI, and
the driver reads scans from it either way; paced, a telegram's bytes come out over its wire
time (first and last byte far apart), unpaced, all at once, as before the flag existed."""

from __future__ import annotations

import argparse
import os
import select
import signal
import subprocess
import sys

import numpy as np
import pytest
from cgamap.daemon import cmd_sim
from cgamap.daemon.cli import UsageError
from cgamap.drivers.lms2xx import Lms2xxDriver, wire_ns

# the sim-device subcommand alone (other subcommands' modules may be mid-change)
BOOT = ("import argparse, sys; from cgamap.daemon import cmd_sim; "
        "p = argparse.ArgumentParser(); cmd_sim.register(p.add_subparsers()); "
        "a = p.parse_args(sys.argv[1:]); sys.exit(a.func(a))")
BAUD = 38400
TELEGRAM = 6 + 3 + 2 * 181 + 1          # a 180°/1° B0 telegram on the wire, bytes


def _parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    cmd_sim.register(p.add_subparsers())
    return p.parse_args(["sim-device", *argv])


def test_flag_parses_and_defaults_off():
    assert _parse("lms2xx").pace_output is False
    assert _parse("lms2xx", "--pace-output").pace_output is True
    cmd_sim._check(_parse("lms2xx", "--pace-output"))          # accepted for lms2xx


@pytest.mark.parametrize("name", ["hokuyo", "cola", "modbus-base"])
def test_flag_is_refused_for_other_twins(name):
    with pytest.raises(UsageError, match="--pace-output: only for lms2xx"):
        cmd_sim._check(_parse(name, "--pace-output"))


def _start(*flags: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-c", BOOT, "sim-device", "lms2xx", "--seed", "1",
                             *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ready, _, _ = select.select([proc.stdout], [], [], 20.0)
    if not ready:
        _stop(proc)
        pytest.fail("lms2xx twin printed no device path within 20 s")
    return proc, proc.stdout.readline().strip()


def _stop(proc: subprocess.Popen) -> int | None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)
        return None


@pytest.mark.parametrize("paced", [True, False], ids=["paced", "unpaced"])
def test_cli_twin_serves_scans_paced_or_not(paced):
    proc, path = _start(*(["--pace-output"] if paced else []))
    try:
        assert path and os.path.exists(path)
        spread = []
        with Lms2xxDriver(path, 0.5, session_baud=BAUD, wire_time=False) as drv:
            for _ in range(6):
                scan = drv.read_scan(3.0)
                assert scan is not None and len(scan.ranges) == 181
                assert np.isfinite(scan.ranges).sum() > 90
                # stamp_ns: arrival of the chunk with the first byte; arrival_ns: the last
                spread.append(drv.arrival_ns - scan.stamp_ns)
    finally:
        code = _stop(proc)
    assert code == 0 and not os.path.exists(path)
    wire = wire_ns(TELEGRAM, BAUD)
    median = float(np.median(spread))
    print(f"paced={paced}: first-to-last byte {median / 1e6:.1f} ms (wire {wire / 1e6:.0f} ms)")
    if paced:
        assert median > 0.5 * wire       # the bytes came over the line's time
    else:
        assert median < 0.5 * wire       # a pty hands over the whole telegram at once
