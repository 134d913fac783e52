"""2D mapping of a long log: `cgamap map build` on 100 laps of the simulated loop world (a
180-beam scan a second, 6 127 scans, LMS-like noise, written as CARMEN), ``--odom-noise
high``, as a subprocess so that its peak memory is its own.  The figures of a log the size of
the larger classic ones (thousands of scans): per-scan time, the finishing pass, the whole
command's wall time and peak resident memory, and the ATE against the simulation's truth.
(Measured once with a scan every half second, 12 254 scans: 714 MB peak, 1 032 MB before the
finishing pass kept its edges as arrays.)"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LAPS = 100
KEYS = ("scans_processed", "segments", "ms_per_scan_median", "ms_per_scan_p95",
        "final_optimisation_ms", "loop_closures", "ate_trans_m", "ate_rot_deg")


def run() -> dict:
    from cgamap.drivers.carmen import write_carmen
    from cgamap.drivers.sim.scanlog import simulated_scans
    from cgamap.drivers.sim.world import get_world

    with tempfile.TemporaryDirectory() as tmp:
        log, out = Path(tmp) / "long.log", Path(tmp) / "m"
        write_carmen(log, simulated_scans(get_world("loop"), laps=LAPS))
        # the build reports its own peak (RUSAGE_CHILDREN would be the largest of every
        # child this benchmark run has had, daemons included)
        code = ("import resource, sys; from cgamap.daemon.cli import main; rc = main(); "
                "print('peak_kb', resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "
                "file=sys.stderr); sys.exit(rc)")
        t0 = time.perf_counter()
        res = subprocess.run([sys.executable, "-c", code, "map", "build", "--log", str(log),
                              "--out", str(out), "--odom-noise", "high", "--seed", "0",
                              "--quiet"], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        if res.returncode:
            raise RuntimeError(f"map build exited {res.returncode}: {res.stderr[-300:]}")
        peak_mb = int(res.stderr.split("peak_kb")[-1].split()[0]) / 1024
        rep = json.loads((out / "report.json").read_text())
    return {"laps": LAPS, "odom_noise": "high", "seed": 0, **{k: rep[k] for k in KEYS},
            "odometry_ate_m": rep["odometry"]["ate_trans_m"], "wall_s": round(wall, 1),
            "peak_rss_mb": round(peak_mb, 1)}
