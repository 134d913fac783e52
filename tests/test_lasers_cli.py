"""``cgamap scan`` against ``cgamap sim-device`` in separate processes, as a user runs them."""

from __future__ import annotations

import json
import select
import signal
import subprocess
import sys

import pytest

# not ``-m cgamap.daemon.cli``: that runs cli.py as __main__, a second copy of the module
CLI = [sys.executable, "-c", "import sys; from cgamap.daemon.cli import main; sys.exit(main())"]


def _start_twin(*args: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(CLI + ["sim-device", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    ready, _, _ = select.select([proc.stdout], [], [], 20.0)
    if not ready:
        proc.kill()
        proc.wait(5)
        pytest.fail("twin printed no address within 20 s")
    return proc, proc.stdout.readline().strip()


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


@pytest.mark.parametrize("model, extra", [("lms2xx", ["--world", "room"]),
                                          ("cola", ["--world", "loop"]),
                                          ("hokuyo", [])])
def test_scan_json_against_twin(model, extra):
    twin, where = _start_twin(model, "--seed", "3", *extra)
    try:
        assert where
        out = subprocess.run(CLI + ["scan", "--device", where, "--model", model, "--count", "3",
                                    "--json"], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        lines = out.stdout.strip().splitlines()
        assert len(lines) == 3
        objs = [json.loads(x) for x in lines]
        assert [o["seq"] for o in objs] == [0, 1, 2]
        for o in objs:
            assert {"seq", "stamp_ns", "angle_min", "angle_increment", "ranges"} <= set(o)
            assert len(o["ranges"]) in (181, 811, 1081)
            assert any(r is not None and r > 0 for r in o["ranges"])
        text = subprocess.run(CLI + ["scan", "--device", where, "--model", model,
                                     "--count", "1"], capture_output=True, text=True,
                              timeout=60)
        assert text.returncode == 0 and text.stdout.startswith("seq 0 ")
    finally:
        _stop(twin)


def test_scan_bad_input_is_one_line_errors(tmp_path):
    r = subprocess.run(CLI + ["scan", "--device", str(tmp_path / "nope"), "--model", "lms2xx"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 1
    assert r.stderr.startswith("cgamap: --device") and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run(CLI + ["scan", "--device", "x", "--model", "lms2xx", "--count", "-1"],
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and "--count" in r.stderr
    r = subprocess.run(CLI + ["scan", "--device", "tcp://127.0.0.1:1", "--model", "cola",
                              "--baud", "9600"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and "only for lms2xx" in r.stderr
