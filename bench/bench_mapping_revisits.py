"""The map and the scan time when the robot keeps coming back: the Intel log driven there
and back (its scans in reverse on the way back) several times, through the mapper with the
daemon's 20 000-node bound and the log's reference poses as odometry (what is measured is
the map and the time, not the trajectory).  Per pass: median and p95 ms per scan, segments,
segments with a copy within 3 cm (:func:`cgamap.mapping.linemap.copies`) and contribution
rows; with 4 passes (the default), the finishing pass's map too, and the time per scan of a
fifth pass while the daemon's finishing pass runs in another thread (the GIL is shared).
``CGAMAP_BENCH_LONG=1`` drives 20 passes (18 200 scans, ~10 min) and runs the finishing
pass after every 4th, as a daemon with ``mapping.optimize_every_s`` does (a job on a
snapshot, then adopted): its time, the largest pose change, and the map after it."""

from __future__ import annotations

import copy
import os
import threading
import time

import numpy as np

from bench import intel

EVERY = 4  # long runs: the daemon's finishing pass after every this many passes


def _drive(m, scans, ref, order) -> np.ndarray:
    """Map ``scans`` in ``order`` with their reference poses as odometry: ms per scan."""
    ms = []
    for k in order:
        s = scans[k]
        t = time.perf_counter()
        m.step(s.ranges, s.angle_min, s.angle_increment, ref[k])
        ms.append((time.perf_counter() - t) * 1e3)
    return np.array(ms)


def _order(p: int, n: int) -> range:
    """Pass ``p``'s scan order: there (even passes) and back (odd ones)."""
    return range(n) if p % 2 == 0 else range(n - 1, -1, -1)


def run() -> dict:
    from cgamap.mapping.jit import warm_up
    from cgamap.mapping.linemap import copies
    from cgamap.mapping.slam2d import Mapper, MapperParams

    if (skip := intel.missing()) is not None:
        return skip
    scans = intel.scans()
    ref = np.array([s.pose_ref for s in scans])
    long = os.environ.get("CGAMAP_BENCH_LONG") == "1"
    passes = 20 if long else 4
    warm_up()
    m = Mapper(MapperParams(max_nodes=20_000), initial_pose=ref[0])
    out: dict = {"passes": passes, "scans_per_pass": len(scans), "per_pass": []}
    for p in range(passes):
        ms = _drive(m, scans, ref, _order(p, len(scans)))
        out["per_pass"].append({
            "ms_per_scan_median": round(float(np.median(ms)), 3),
            "ms_per_scan_mean": round(float(np.mean(ms)), 3),
            "ms_per_scan_p95": round(float(np.percentile(ms, 95)), 2),
            "segments": len(m.map), "copies_3cm": copies(m.map.a, m.map.b),
            "contribution_rows": len(m.map.c_seg)})
        if long and (p + 1) % EVERY == 0:
            t = time.perf_counter()
            got = m.apply_finish(m.live_finishing_job().run())
            out["per_pass"][-1]["finishing_pass"] = {
                "s": round(time.perf_counter() - t, 1), "nodes": got["nodes"],
                "max_shift_m": round(got["max_shift_m"], 3), "segments": len(m.map),
                "copies_3cm": copies(m.map.a, m.map.b)}
    if not long:
        out["beside_the_pass"] = _beside_the_pass(
            copy.deepcopy(m), scans, ref, _order(passes, len(scans))[:400])
        t = time.perf_counter()
        m.finish()
        out["finished"] = {"segments": len(m.map), "copies_3cm": copies(m.map.a, m.map.b),
                           "finishing_pass_s": round(time.perf_counter() - t, 1)}
    return out


def _beside_the_pass(m, scans, ref, order: range) -> dict:
    """Per-scan time of the scans ``order`` (of the next pass) mapped while the daemon's
    finishing pass (a job on a snapshot) runs in a thread of the same process, next to the
    same scans mapped with nothing beside them (on a copy: the two must start alike)."""

    def figures(ms: np.ndarray) -> dict:
        return {"ms_per_scan_median": round(float(np.median(ms)), 3),
                "ms_per_scan_p95": round(float(np.percentile(ms, 95)), 2),
                "ms_per_scan_max": round(float(ms.max()), 1)}

    alone = _drive(copy.deepcopy(m), scans, ref, order)
    job = m.live_finishing_job()
    worker = threading.Thread(target=job.run)
    t = time.perf_counter()
    worker.start()
    beside = _drive(m, scans, ref, order)
    overlapped = worker.is_alive()  # the pass outlasted the scans: all of them were beside it
    worker.join()
    return {"scans": len(order), "alone": figures(alone), "beside": figures(beside),
            "pass_s": round(time.perf_counter() - t, 1), "pass_outlasted_scans": overlapped}
