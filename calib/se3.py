"""Small rigid-motion helpers on (..., 4, 4) homogeneous matrices, vectorised over poses.

The calibration works on matrices where it talks to OpenCV and files, and on motors (the CGA
core) where the geometry is (screw axes, the linear hand-eye step).  These helpers are the
matrix side: exp/log of rotations, inverses, random motions and error metrics.
"""

from __future__ import annotations

import numpy as np


def skew(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices [w]x."""
    w = np.asarray(w, dtype=float)
    z = np.zeros(w.shape[:-1])
    return np.stack([
        np.stack([z, -w[..., 2], w[..., 1]], -1),
        np.stack([w[..., 2], z, -w[..., 0]], -1),
        np.stack([-w[..., 1], w[..., 0], z], -1),
    ], -2)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrices of rotation vectors (..., 3) (Rodrigues)."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices; robust near 0 and near pi."""
    R = np.asarray(R, dtype=float)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], -1)
    s = 0.5 * np.linalg.norm(v, axis=-1)
    c = np.clip(0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0), -1.0, 1.0)
    th = np.arctan2(s, c)
    scale = np.where(s < 1e-10, 0.5 + th**2 / 12.0, th / (2.0 * np.where(s < 1e-10, 1.0, s)))
    w = scale[..., None] * v
    near_pi = c < -0.99
    if np.any(near_pi):  # axis from the symmetric part: R + I = 2 a a^T (1 - cos) / ...
        Rp = R[near_pi]
        B = 0.5 * (Rp + np.eye(3))
        k = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        col = np.take_along_axis(B, k[:, None, None].repeat(3, 1), axis=2)[..., 0]
        a = col / np.linalg.norm(col, axis=-1, keepdims=True)
        vp = v[near_pi]
        sgn = np.where(np.einsum("ni,ni->n", a, vp) < 0, -1.0, 1.0)
        w[near_pi] = (sgn * th[near_pi])[:, None] * a
    return w


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    H = np.zeros(np.broadcast_shapes(R.shape[:-2], t.shape[:-1]) + (4, 4))
    H[..., :3, :3] = R
    H[..., :3, 3] = t
    H[..., 3, 3] = 1.0
    return H


def inv(H: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms."""
    R = H[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make_pose(Rt, -np.einsum("...ij,...j->...i", Rt, H[..., :3, 3]))


def project_rotation(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to (..., 3, 3) matrices."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, -1] *= d[..., None]
    return U @ Vt


def rotation_error_deg(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle of Ra^T Rb in degrees."""
    return np.degrees(np.linalg.norm(so3_log(np.swapaxes(Ra, -1, -2) @ Rb), axis=-1))


def pose_errors(Ha: np.ndarray, Hb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rotation error in degrees, translation error in metres) between poses."""
    rot = rotation_error_deg(Ha[..., :3, :3], Hb[..., :3, :3])
    trans = np.linalg.norm(Ha[..., :3, 3] - Hb[..., :3, 3], axis=-1)
    return rot, trans


def rpy_from_matrix(R: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (radians) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    R = np.asarray(R, dtype=float)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def random_rotations(rng: np.random.Generator, n: int, max_angle: float) -> np.ndarray:
    """n rotations about uniform random axes, angles uniform in [0, max_angle]."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    return so3_exp(axis * rng.uniform(0.0, max_angle, size=(n, 1)))


def perturb(H: np.ndarray, rng: np.random.Generator, sigma_rot: float,
            sigma_trans: float) -> np.ndarray:
    """Poses with Gaussian noise: rotation vector and translation, per axis sigma (rad, m)."""
    n = H.shape[:-2]
    dR = so3_exp(rng.normal(scale=sigma_rot, size=n + (3,)))
    out = H.copy()
    out[..., :3, :3] = dR @ H[..., :3, :3]
    out[..., :3, 3] += rng.normal(scale=sigma_trans, size=n + (3,))
    return out
