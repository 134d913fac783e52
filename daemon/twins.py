"""Start and stop simulated device twins as subprocesses (for ``cgamap demo`` and the tests).

A twin is started as ``python -m cgamap.daemon.twins NAME [options]``, which runs the module
named in ``cmd_sim.TWINS`` without loading the whole CLI; its first stdout line is where to
connect (a pty path or host:port).
"""

from __future__ import annotations

import argparse
import importlib
import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass

from cgamap.daemon.cmd_sim import TWINS


@dataclass
class Twin:
    name: str
    proc: subprocess.Popen
    where: str
    started_ns: int  # monotonic ns just before the twin was started (its clock's epoch)

    @property
    def url(self) -> str:
        if self.where.startswith("/"):
            return f"serial://{self.where}"
        return f"tcp://{self.where}"

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)

    def stop(self, timeout: float = 5.0) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        for f in (self.proc.stdout, self.proc.stderr):
            if f is not None:
                f.close()


def start_twin(name: str, world: str = "corridor", seed: int = 0, fault_rate: float = 0.0,
               timeout: float = 20.0, stderr=None, extra: list[str] | None = None) -> Twin:
    """Start twin ``name`` and wait for its first line (where to connect)."""
    if name not in TWINS:
        raise ValueError(f"unknown twin {name!r} (one of {', '.join(sorted(TWINS))})")
    cmd = [sys.executable, "-m", "cgamap.daemon.twins", name, "--world", world,
           "--seed", str(seed), "--fault-rate", str(fault_rate), *(extra or [])]
    t0 = time.monotonic_ns()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=stderr or subprocess.DEVNULL,
                            text=True, start_new_session=True)
    deadline = time.monotonic() + timeout
    line = ""
    while time.monotonic() < deadline and proc.poll() is None:
        ready, _, _ = select.select([proc.stdout], [], [], 0.2)
        if ready:
            line = proc.stdout.readline().strip()
            break
    if not line:
        proc.kill()
        proc.wait(5)
        raise RuntimeError(f"twin {name} did not start (exit {proc.returncode})")
    return Twin(name, proc, line, t0)


def twin_available(name: str) -> bool:
    try:
        importlib.import_module(TWINS[name])
    except (ImportError, KeyError):
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m cgamap.daemon.twins")
    p.add_argument("name", choices=sorted(TWINS))
    p.add_argument("--world", default="corridor")
    p.add_argument("--fault-rate", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--rtu", action="store_true")
    args = p.parse_args(argv)
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    return int(importlib.import_module(TWINS[args.name]).main(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
