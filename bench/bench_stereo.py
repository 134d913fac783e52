"""Stereo path speed and accuracy: StereoSGBM (3-way) on a 640x400 pair with 64 disparities,
the synthetic world's render time, disparity -> points -> global frame for one frame, and the
depth accuracy of the synthetic corridor and the Middlebury bad-pixel rates."""

from __future__ import annotations

import time

import numpy as np
from cgamap.drivers.sim.stereo_render import SyntheticGrabber, render_pair
from cgamap.drivers.stereo import frame_motor, frame_points
from cgamap.drivers.stereo_points import disparity_to_points, points_to_global
from cgamap.drivers.stereo_sgbm import SgbmParams, compute_disparity, make_matcher

MIDDLEBURY = [("tsukuba", "im3.png", "im4.png", "disp3.pgm", 16, 32),
              ("venus", "im2.png", "im6.png", "disp2.pgm", 8, 32),
              ("teddy", "im2.png", "im6.png", "disp2.png", 4, 64),
              ("cones", "im2.png", "im6.png", "disp2.png", 4, 64)]


def _times_ms(fn, repeat: int) -> tuple[float, float]:
    """(best, median) wall time in ms over ``repeat`` runs after one warm-up."""
    fn()
    ts = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return min(ts) * 1e3, float(np.median(ts)) * 1e3


def _middlebury() -> dict:
    try:
        import cv2
        from conftest import data_dir
    except ImportError:
        return {}
    out = {}
    for scene, l, r, g, scale, nd in MIDDLEBURY:
        base = data_dir() / "stereo" / "middlebury" / scene
        if not (base / g).exists():
            continue
        L = cv2.imread(str(base / l), cv2.IMREAD_GRAYSCALE)
        R = cv2.imread(str(base / r), cv2.IMREAD_GRAYSCALE)
        G = cv2.imread(str(base / g), cv2.IMREAD_UNCHANGED).astype(float) / scale
        d = compute_disparity(L, R, SgbmParams(num_disparities=nd))
        known = G > 0
        known[:, :nd] = False
        valid = known & np.isfinite(d)
        out[scene] = {
            "bad1_matched": round(float((np.abs(d - G)[valid] > 1).mean()), 4),
            "bad1_all": round(float(((np.abs(d - G) > 1) | ~np.isfinite(d))[known].mean()), 4),
            "density": round(float(valid.sum() / known.sum()), 4),
        }
    return out


def run() -> dict:
    import cv2

    threads = cv2.getNumThreads()
    g = SyntheticGrabber("corridor", pose=(3.0, 0.0, 0.0), tilt=0.2, seed=1)
    M, _, _, _ = g.camera_motor_at(0.0)
    left, right, depth = render_pair(g.scene, M, g.calib, g.size)
    params = SgbmParams(num_disparities=64, block_size=5)
    matcher = make_matcher(params)
    sgbm_best, sgbm_med = _times_ms(lambda: compute_disparity(left, right, params, matcher), 10)
    render_best, render_med = _times_ms(lambda: render_pair(g.scene, M, g.calib, g.size), 3)

    frame = g.grab()
    M_GC = frame_motor(frame, g.mount)
    reproj_best, _ = _times_ms(lambda: disparity_to_points(frame.disparity, frame.calib), 10)
    pts = frame_points(frame)
    glob_best, _ = _times_ms(lambda: points_to_global(pts, M_GC), 10)
    total_best, _ = _times_ms(lambda: points_to_global(
        disparity_to_points(frame.disparity, frame.calib), frame_motor(frame, g.mount)), 10)

    est = frame.depth_image()
    ok = np.isfinite(est) & np.isfinite(frame.ground_truth)
    rel = np.abs(est - frame.ground_truth)[ok] / frame.ground_truth[ok]
    return {
        "opencv_threads": threads,
        "sgbm_640x400_64disp_ms": {"best": round(sgbm_best, 2), "median": round(sgbm_med, 2)},
        "synthetic_render_pair_640x400_ms": {"best": round(render_best, 1),
                                             "median": round(render_med, 1),
                                             "quads": len(g.scene)},
        "points_per_frame": int(len(pts)),
        "reproject_ms": round(reproj_best, 2),
        "points_to_global_ms": round(glob_best, 2),
        "disparity_to_global_total_ms": round(total_best, 2),
        "synthetic_corridor_depth": {
            "density": round(float(ok.mean()), 4),
            "median_rel_error": round(float(np.median(rel)), 5),
            "p90_rel_error": round(float(np.percentile(rel, 90)), 5),
        },
        "middlebury_sgbm_block5": _middlebury(),
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
