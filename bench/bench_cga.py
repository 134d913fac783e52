"""CGA kernel speed: moving 1e5 points by a motor (fast path and full sandwich) against a
numpy 4x4 homogeneous transform in the same run, and geometric products per second."""

from __future__ import annotations

import time

import numpy as np
from cgamap.cga import Multivector, apply_points, apply_points_sandwich, motor_from_matrix
from cgamap.cga.selfcheck import random_pose_matrix


def _best_ms(fn, repeat: int) -> float:
    fn()
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best * 1e3


def run(n: int = 100_000) -> dict:
    rng = np.random.default_rng(0)
    x = rng.uniform(-10, 10, size=(n, 3))
    H = random_pose_matrix(rng, 1)[0]
    M = motor_from_matrix(H)

    def homogeneous_4x4():
        xh = np.empty((n, 4))
        xh[:, :3] = x
        xh[:, 3] = 1.0
        return (xh @ H.T)[:, :3]

    ref = homogeneous_4x4()
    err_fast = float(np.abs(apply_points(M, x) - ref).max())
    err_sandwich = float(np.abs(apply_points_sandwich(M, x) - ref).max())
    t_ref = _best_ms(homogeneous_4x4, 20)
    t_rigid = _best_ms(lambda: x @ H[:3, :3].T + H[:3, 3], 20)  # the leanest numpy form
    t_fast = _best_ms(lambda: apply_points(M, x), 20)
    t_sandwich = _best_ms(lambda: apply_points_sandwich(M, x), 5)
    A = Multivector(rng.normal(size=(n, 32)))
    B = Multivector(rng.normal(size=(n, 32)))
    t_gp = _best_ms(lambda: A * B, 3)
    return {
        "points": n,
        "matrix4x4_ms": round(t_ref, 3),
        "rotation_plus_translation_ms": round(t_rigid, 3),
        "motor_fast_path_ms": round(t_fast, 3),
        "motor_sandwich_ms": round(t_sandwich, 3),
        "fast_path_ratio_to_4x4": round(t_fast / t_ref, 2),
        "sandwich_ratio_to_4x4": round(t_sandwich / t_ref, 2),
        "sandwich_ratio_to_rotation_plus_translation": round(t_sandwich / t_rigid, 2),
        "targets": {"fast_path_ratio": 3.0, "sandwich_ratio": 20.0},
        "max_abs_error_fast_path": err_fast,
        "max_abs_error_sandwich": err_sandwich,
        "geometric_products_per_s_dense": round(n / (t_gp / 1e3)),
    }
