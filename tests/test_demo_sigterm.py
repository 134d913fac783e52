"""A demo stopped by SIGTERM (a CI timeout, `kill`) stops its twins and daemon as Ctrl-C does:
the twins run in sessions of their own, so nothing else would."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def test_sigterm_stops_the_demos_twins(tmp_path):
    code = "import sys; from cgamap.daemon.cli import main; sys.exit(main())"
    demo = subprocess.Popen([sys.executable, "-c", code, "demo", "--duration", "60",
                             "--out", str(tmp_path / "out"), "--no-camera"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen, kids = "", []
    try:
        # until the first progress line: the twins and the daemon are all running
        deadline = time.monotonic() + 60
        while "] pose" not in seen and time.monotonic() < deadline:
            ready, _, _ = select.select([demo.stdout], [], [], 0.5)
            if ready:
                line = demo.stdout.readline()
                if not line:
                    break
                seen += line
        assert "] pose" in seen, seen
        kids = _children(demo.pid)
        assert len(kids) >= 3, (kids, seen)  # the laser and base twins and cgamapd at least
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(30) == 128 + signal.SIGTERM
        deadline = time.monotonic() + 15
        while any(_alive(k) for k in kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        left = [k for k in kids if _alive(k)]
        assert not left, f"left running: {left}"
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait(5)
        for k in kids + _children(demo.pid):  # nothing left running, whatever failed
            if _alive(k):
                os.kill(k, signal.SIGKILL)
