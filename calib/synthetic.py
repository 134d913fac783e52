"""Synthetic hand-eye problems with a known mount, for tests and the benchmark.

A head turns about random axes (up to ``max_angle``) and moves within a few decimetres; the
camera looks at a target about ``target_dist`` ahead.  Noise is Gaussian per axis on both
measured poses: rotation vector (rad) and translation (m), applied in the parent frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from cgamap.drivers.stereo_points import R_HEAD_OPTICAL

from .se3 import inv, make_pose, perturb, random_rotations, so3_exp


@dataclass
class Problem:
    base_T_head: np.ndarray  # (n, 4, 4), noisy
    cam_T_target: np.ndarray  # (n, 4, 4), noisy
    head_T_cam: np.ndarray  # (4, 4), the truth
    base_T_target: np.ndarray  # (4, 4), the truth


def random_mount(rng: np.random.Generator) -> np.ndarray:
    """A camera mount: optical axis roughly forward, a few centimetres off the head origin."""
    R = random_rotations(rng, 1, np.radians(20.0))[0] @ R_HEAD_OPTICAL  # cam -> head
    return make_pose(R, rng.uniform(-0.1, 0.1, 3))


def make_problem(rng: np.random.Generator, n: int = 20, sigma_rot_deg: float = 0.0,
                 sigma_trans_m: float = 0.0, max_angle_deg: float = 45.0,
                 target_dist: float = 0.8) -> Problem:
    X = random_mount(rng)
    Rh = random_rotations(rng, n, np.radians(max_angle_deg))
    H = make_pose(Rh, rng.uniform(-0.2, 0.2, (n, 3)))
    # The target sits target_dist ahead of the camera at the first pose, facing it.
    cam0 = H[0] @ X
    Y = cam0 @ make_pose(so3_exp(rng.normal(scale=0.2, size=3)), [0.0, 0.0, target_dist])
    C = inv(X) @ inv(H) @ Y
    s_r, s_t = np.radians(sigma_rot_deg), sigma_trans_m
    if s_r > 0 or s_t > 0:
        H = perturb(H, rng, s_r, s_t)
        C = perturb(C, rng, s_r, s_t)
    return Problem(H, C, X, Y)
