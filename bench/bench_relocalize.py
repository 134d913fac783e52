"""Relocalisation on the real Intel log: 200 trials on the built map (median, p95), and the
all-rotation fallback sweep for cluttered scans -- how often it runs, what it costs, how many
grid positions it reads, and that this count stays put when the map's grid is made 4x larger
with empty space around (it reads only the free-space band near walls)."""

from __future__ import annotations

import time

import numpy as np

from .intel import LOG, build, missing
from .intel import scans as intel_scans


def _fallback_figures(lmap, scans, idx) -> dict:
    """Run the trials' scans again with the fallback sweep instrumented (counts, CPU time)."""
    from cgamap.mapping import relocalize as R
    from cgamap.mapping.segments import extract_segments

    P = R.RelocParams()
    field = R.DistanceField(lmap, P.field_resolution)
    field.seg_id  # noqa: B018  (built once, not part of a trial)
    calls: list[dict] = []
    orig = R.fallback_sweep

    def counted(f, pts, Q, reach=None, stats=None, near=None):
        st: dict = {}
        t = time.process_time()
        out = orig(f, pts, Q, reach, st, near=near)
        st["ms"] = (time.process_time() - t) * 1e3
        st["reach_m"] = reach
        calls.append(st)
        return out

    segs = [extract_segments(scans[int(i)].ranges, scans[int(i)].angle_min,
                             scans[int(i)].angle_increment) for i in idx]
    R.fallback_sweep = counted
    try:
        trial_ms, fb_trial = [], []
        for seg in segs:
            n0 = len(calls)
            t = time.process_time()
            R.relocalize(lmap, seg, field, P)
            trial_ms.append((time.process_time() - t) * 1e3)
            fb_trial.append(len(calls) > n0)
    finally:
        R.fallback_sweep = orig
    trial_ms, fb_trial = np.array(trial_ms), np.array(fb_trial)
    out = {"trials": len(idx), "fallback_trials": int(fb_trial.sum())}
    if calls:
        out.update(
            sweep_cpu_ms_median=round(float(np.median([c["ms"] for c in calls])), 2),
            positions_median=int(np.median([c["positions"] for c in calls])),
            band_median=int(np.median([c["band"] for c in calls])),
            grid_positions=int(np.prod(field.grid_shape(
                int(round(P.fallback_grid / field.res))))),
            reach_m_median=round(float(np.median([c["reach_m"] for c in calls])), 2),
            reads_per_sweep=int(np.median([c["positions"] * c["rotations"] * c["points"]
                                           for c in calls])),
            fallback_trial_cpu_ms_median=round(float(np.median(trial_ms[fb_trial])), 2),
            other_trial_cpu_ms_median=round(float(np.median(trial_ms[~fb_trial])), 2),
        )
        # the same sweeps on the map's field with a border making its grid 4x larger
        lo, hi = field.lo + 2.0, field.lo + field.size * field.res - 2.0   # the walls' box
        w, h = hi - lo
        # (w + 2b)(h + 2b) = 4 (w + 4)(h + 4), solved for the border b
        border = (-(w + h) + np.sqrt((w - h) ** 2 + 16 * (w + 4) * (h + 4))) / 4
        big = R.DistanceField(lmap, P.field_resolution, border=float(border))
        pos_big, ms_big = [], []
        for seg in [s for s, f in zip(segs, fb_trial, strict=True) if f]:
            pts = seg.points
            if len(pts) > P.verify_points:
                pts = pts[np.linspace(0, len(pts) - 1, P.verify_points).astype(int)]
            st: dict = {}
            t = time.process_time()
            orig(big, pts, P, R.reach_bound(seg.points, P, big.res), st)
            ms_big.append((time.process_time() - t) * 1e3)
            pos_big.append(st["positions"])
        out["grid4x"] = {
            "border_m": round(float(border), 1),
            "grid_positions": int(np.prod(big.grid_shape(
                int(round(P.fallback_grid / big.res))))),
            "positions_median": int(np.median(pos_big)),
            "sweep_cpu_ms_median": round(float(np.median(ms_big)), 2),
        }
    return out


def run() -> dict:
    from cgamap.mapping.offline import relocalize_trials

    if missing():
        return missing()
    res = build(0)
    scans = list(intel_scans())
    out: dict = {"log": LOG, "odom_noise": "high", "map_seed": 0, "segments": len(res.map)}
    out["relocalize"] = relocalize_trials(res.map, scans, 200, seed=0,
                                          alignment=res.report["alignment_to_reference"])
    idx = np.random.default_rng(0).choice(len(scans), size=200, replace=False)  # the same
    out["fallback"] = _fallback_figures(res.map, scans, idx)
    return out


if __name__ == "__main__":
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    print(json.dumps(run(), indent=2))
