"""Hand-eye calibration in motor algebra (Bayro-Corrochano, Daniilidis & Sommer, 2000).

The camera sits on the pan-tilt head; the unknown mount is X = head_T_cam.  Pose pair i gives
H_i = base_T_head (from the joints) and C_i = cam_T_target (from the camera), and the target
stays put: Z_i = H_i X C_i = base_T_target for every i.  Two pairs give one motion equation
A X = X B with A = H_j^-1 H_i (the head's motion) and B = C_j C_i^-1 (the camera's).

1. Linear step, in motor algebra: A and B are motors; their bivector parts are their screw
   axes (lines, scaled by sin of the half angle, with the pitch in the e_i einf part), and
   A X = X B says the line of A is the line of B carried by X.  Written as
   <A>_2 X - X <B>_2 = 0 it is linear in the 8 coefficients of X (1, e23, e31, e12, e1inf,
   e2inf, e3inf, e123inf); stacking all motions and taking the SVD leaves a 2-dimensional null
   space, and the motor conditions X ~X = 1 (scalar part 1, e123inf part 0) pick the solution
   inside it: rotation and translation in one step.
2. Refinement (``calib/refine.py``): least squares over X and the target pose together on the
   absolute residuals, noise model learnt from the data, Huber loss, outlier pose pairs
   rejected; 3. an uncertainty estimate of X (sandwich covariance).

Degenerate input (all rotations about one axis leave X free to turn about it and slide along
it) is refused before solving, naming the missing excitation.
"""

from __future__ import annotations

import numpy as np
from cgamap.cga import Multivector, blade_index, motor_from_matrix, motor_to_matrix

from .refine import HandEyeResult, mean_pose, refine, residuals
from .se3 import inv, make_pose, project_rotation, so3_log

METHODS = ("motor", "tsai", "park", "horaud", "andreff", "daniilidis")

# The motor subalgebra (isomorphic to the dual quaternions): coordinates of X.
_MOTOR_BASIS_NAMES = ("1", "e23", "e31", "e12", "e1inf", "e2inf", "e3inf", "e123inf")


class DegenerateMotionError(ValueError):
    """The pose pairs do not excite enough rotation axes to determine the mount."""


def _motor_basis() -> Multivector:
    v = np.zeros((8, 32))
    v[0, 0] = 1.0
    v[1, blade_index("e23")] = 1.0
    v[2, blade_index("e13")] = -1.0  # e31 = -e13
    v[3, blade_index("e12")] = 1.0
    for k, i in enumerate((1, 2, 3)):  # e_i einf = e_i+ + e_i-
        v[4 + k, blade_index(f"e{i}+")] = 1.0
        v[4 + k, blade_index(f"e{i}-")] = 1.0
    v[7, blade_index("e123+")] = 1.0
    v[7, blade_index("e123-")] = 1.0
    return Multivector(v)


_BASIS = _motor_basis()
# Coordinates of a motor-subalgebra element in _BASIS: the pseudo-inverse of the basis matrix.
_COORDS = np.linalg.pinv(_BASIS.v)  # (32, 8)
_E123INF = 7


def _motor_gram() -> tuple[np.ndarray, np.ndarray]:
    """Bilinear forms of X ~X on the 8 coordinates: its scalar part and its e123inf part."""
    prod = (_BASIS[:, None] * _BASIS[None, :].reverse()).v @ _COORDS  # (8, 8, 8)
    S = 0.5 * (prod[..., 0] + prod[..., 0].T)
    Q = 0.5 * (prod[..., _E123INF] + prod[..., _E123INF].T)
    return S, Q


_GRAM_S, _GRAM_Q = _motor_gram()


def mount_motor(X: np.ndarray) -> dict[str, float]:
    """The mount as a CGA motor M = T R, by its coefficients on 1, e23, e31, e12, e1inf,
    e2inf, e3inf, e123inf (scalar part >= 0)."""
    c = motor_from_matrix(X).v @ _COORDS
    c = -c if c[0] < 0 else c
    return {name: float(v) for name, v in zip(_MOTOR_BASIS_NAMES, c, strict=True)}


# ---- input checks ------------------------------------------------------------------------

def _as_poses(x, name: str) -> np.ndarray:
    H = np.asarray(x, dtype=float)
    if H.ndim != 3 or H.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected (n, 4, 4) poses, got shape {H.shape}")
    if not np.all(np.isfinite(H)):
        raise ValueError(f"{name}: non-finite values")
    R = H[:, :3, :3]
    err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((err > 1e-3) | (np.linalg.det(R) < 0))
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}]: rotation part is not a rotation matrix")
    H = H.copy()
    H[:, :3, :3] = project_rotation(R)  # remove round-off from files (e.g. 6-digit values)
    H[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return H


def motion_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """All index pairs i < j: every pair of pose pairs gives one motion."""
    i, j = np.triu_indices(n, k=1)
    return i, j


def relative_motions(H: np.ndarray, C: np.ndarray, i: np.ndarray, j: np.ndarray):
    """A = H_j^-1 H_i (head motion), B = C_j C_i^-1 (camera motion): A X = X B."""
    return inv(H[j]) @ H[i], C[j] @ inv(C[i])


def check_excitation(H: np.ndarray, pan=None, tilt=None, min_deg: float = 1.0) -> None:
    """Refuse motions that turn about one axis only (or not at all), naming what is missing.

    The head's relative rotation vectors are collected in the head frame; the second
    principal direction of their scatter must carry an RMS rotation of ``min_deg`` or more.
    """
    n = len(H)
    if n < 3:
        raise DegenerateMotionError(
            f"need at least 3 pose pairs (2 motions about non-parallel axes), got {n}")
    i, j = motion_pairs(n)
    w = so3_log(np.swapaxes(H[j, :3, :3], 1, 2) @ H[i, :3, :3])
    ev, evec = np.linalg.eigh(w.T @ w / len(w))
    rms = np.degrees(np.sqrt(np.clip(ev[::-1], 0.0, None)))
    if rms[0] < min_deg:
        raise DegenerateMotionError(
            "degenerate motions: the head hardly rotates between pose pairs "
            f"(RMS {rms[0]:.2f} deg); move the joints (both pan and tilt) between poses")
    if rms[1] < min_deg:
        axis = evec[:, -1] * np.sign(evec[np.argmax(np.abs(evec[:, -1])), -1])
        joint = ""
        for name, q in (("tilt", tilt), ("pan", pan)):
            if q is not None and len(q) == n and np.ptp(np.asarray(q, float)) < np.radians(0.5):
                joint = f"; the {name} joint never moves (all at {float(np.mean(q)):.3f} rad)"
                break
        raise DegenerateMotionError(
            "degenerate motions: all head rotations are about one axis "
            f"({axis[0]:+.2f}, {axis[1]:+.2f}, {axis[2]:+.2f}) in the head frame{joint}; "
            "rotation about a second, non-parallel axis is missing (RMS "
            f"{rms[1]:.2f} deg) - add poses that move the other joint")


# ---- 1. the linear step in motor algebra ---------------------------------------------------

def _product_tensor() -> np.ndarray:
    """T[a, c, r]: coordinate r of basis_a * basis_c (the motor subalgebra is closed)."""
    return (_BASIS[:, None] * _BASIS[None, :]).v @ _COORDS


_PRODUCT = _product_tensor()


def _motion_rows(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(6K, 8) rows of <A>_2 X - X <B>_2 = 0 for K motions given as 4x4 matrices.

    <A>_2 is the screw line of A (scaled by sin of the half angle, the pitch in the e_i einf
    part); the products run through the geometric-product tensor of the motor basis."""
    a, b = motor_from_matrix(A).v @ _COORDS, motor_from_matrix(B).v @ _COORDS  # (K, 8)
    # Same screw angle on both sides: align the motor signs by their scalar parts.  Near a
    # half turn both scalar parts vanish and noise can pick the wrong sign: such motions
    # are dropped while enough others remain (the refinement still uses their poses).
    b = b * np.where(a[:, :1] * b[:, :1] < 0, -1.0, 1.0)
    clear = (np.abs(a[:, 0]) > 0.02) | (np.abs(b[:, 0]) > 0.02)
    if clear.sum() >= 2:
        a, b = a[clear], b[clear]
    la, lb = a.copy(), b.copy()
    la[:, [0, _E123INF]] = 0.0  # keep the bivector (line) parts
    lb[:, [0, _E123INF]] = 0.0
    # E[k, c, r]: coordinate r of la_k * basis_c - basis_c * lb_k.
    E = np.einsum("ka,acr->kcr", la, _PRODUCT) - np.einsum("kb,cbr->kcr", lb, _PRODUCT)
    return np.swapaxes(E[:, :, 1:7], 1, 2).reshape(-1, 8)


def _motor_from_nullspace(v1: np.ndarray, v2: np.ndarray) -> np.ndarray:
    """The unit motor in span(v1, v2): e123inf part 0 and scalar part 1 of X ~X."""
    a, b, c = v1 @ _GRAM_Q @ v1, 2.0 * v1 @ _GRAM_Q @ v2, v2 @ _GRAM_Q @ v2
    # X = cos(f) v1 + sin(f) v2: a cos^2 + b cos sin + c sin^2 = 0, i.e.
    # (a + c)/2 + (a - c)/2 cos 2f + b/2 sin 2f = 0.
    p, q, r = 0.5 * (a + c), 0.5 * (a - c), 0.5 * b
    amp = np.hypot(q, r)
    psi = np.arctan2(r, q)
    d = np.arccos(np.clip(-p / amp, -1.0, 1.0)) if amp > 1e-300 else 0.0
    best, best_s = None, -1.0
    for f in (0.5 * (psi + d), 0.5 * (psi - d)):
        x = np.cos(f) * v1 + np.sin(f) * v2
        s = x @ _GRAM_S @ x
        if s > best_s:
            best, best_s = x, s
    return best / np.sqrt(best_s)


def solve_linear(H: np.ndarray, C: np.ndarray, pairs=None) -> np.ndarray:
    """head_T_cam from the SVD of the stacked screw-line equations (rotation and translation
    together, Bayro-Corrochano et al. 2000 / Daniilidis 1999)."""
    i, j = motion_pairs(len(H)) if pairs is None else pairs
    A, B = relative_motions(H, C, i, j)
    rows = _motion_rows(A, B)
    _, _, Vt = np.linalg.svd(rows, full_matrices=False)
    x = _motor_from_nullspace(Vt[-2], Vt[-1])
    X = motor_to_matrix(Multivector(x @ _BASIS.v))
    X[:3, :3] = project_rotation(X[:3, :3])
    return X


def _linear_with_screening(H: np.ndarray, C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear solution, re-solved without pose pairs whose motions disagree with it.

    A bad pose pair spoils every motion it takes part in; its median motion residual stands
    out against the others'.  Returns (X, keep mask)."""
    n = len(H)
    X = solve_linear(H, C)
    i, j = motion_pairs(n)
    A, B = relative_motions(H, C, i, j)
    # Scale-free motion residual: rotation (rad) plus translation relative to the motion size,
    # summed over both directions of each motion so that the pair order does not matter.
    scale = np.median(np.linalg.norm(A[:, :3, 3], axis=-1)) + 1e-12
    r = np.zeros(len(A))
    for A_, B_ in ((A, B), (inv(A), inv(B))):
        AX, XB = A_ @ X, X @ B_
        r += np.linalg.norm(so3_log(np.swapaxes(AX[:, :3, :3], 1, 2) @ XB[:, :3, :3]), axis=-1)
        r += np.linalg.norm(AX[:, :3, 3] - XB[:, :3, 3], axis=-1) / scale
    per_pose = np.array([np.median(r[(i == k) | (j == k)]) for k in range(n)])
    med = np.median(per_pose)
    mad = 1.4826 * np.median(np.abs(per_pose - med)) + 1e-12
    keep = per_pose <= med + 5.0 * mad + 1e-9
    if keep.sum() >= max(3, n // 2) and not keep.all():
        X = solve_linear(H[keep], C[keep])
    else:
        keep = np.ones(n, bool)
    return X, keep


# ---- the solvers ---------------------------------------------------------------------------

def solve_motor(base_T_head, cam_T_target, pan=None, tilt=None,
                refine_solution: bool = True) -> HandEyeResult:
    """Our solver: motor-algebra SVD, then robust refinement (see the module docstring)."""
    H = _as_poses(base_T_head, "base_T_head")
    C = _as_poses(cam_T_target, "cam_T_target")
    if len(H) != len(C):
        raise ValueError(f"{len(H)} base_T_head poses but {len(C)} cam_T_target poses")
    check_excitation(H, pan, tilt)
    X_lin, keep = _linear_with_screening(H, C)
    if not refine_solution:
        return HandEyeResult(head_T_cam=X_lin, method="motor-linear", linear=X_lin,
                             inliers=keep)
    out = refine(H, C, X_lin, keep0=keep)
    out.linear = X_lin
    return out


_CV_METHODS = {
    "tsai": "CALIB_HAND_EYE_TSAI",
    "park": "CALIB_HAND_EYE_PARK",
    "horaud": "CALIB_HAND_EYE_HORAUD",
    "andreff": "CALIB_HAND_EYE_ANDREFF",
    "daniilidis": "CALIB_HAND_EYE_DANIILIDIS",
}


def solve_opencv(base_T_head, cam_T_target, method: str) -> HandEyeResult:
    """One of OpenCV's five (cv2.calibrateHandEye), for comparison."""
    import cv2

    if not hasattr(cv2, "calibrateHandEye"):
        raise RuntimeError(f"OpenCV {cv2.__version__} lacks calibrateHandEye (use 4.x)")
    H = _as_poses(base_T_head, "base_T_head")
    C = _as_poses(cam_T_target, "cam_T_target")
    try:
        R, t = cv2.calibrateHandEye(
            list(H[:, :3, :3]), list(H[:, :3, 3:]), list(C[:, :3, :3]), list(C[:, :3, 3:]),
            method=getattr(cv2, _CV_METHODS[method]))
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1].split(") ", 1)[-1]
        raise RuntimeError(f"OpenCV's {method} method failed on these pairs: {msg}") from None
    X = make_pose(np.asarray(R), np.asarray(t).reshape(3))
    res, _ = residuals(X, mean_pose(H @ X @ C), H, C)
    return HandEyeResult(
        head_T_cam=X, method=method, inliers=np.ones(len(H), bool),
        residual_rot_deg=np.degrees(np.linalg.norm(res[:, :3], axis=-1)),
        residual_trans_m=np.linalg.norm(res[:, 3:], axis=-1))


def solve(base_T_head, cam_T_target, method: str = "motor", pan=None, tilt=None
          ) -> HandEyeResult:
    """Dispatch: ``motor`` (ours) or one of OpenCV's five."""
    if method == "motor":
        return solve_motor(base_T_head, cam_T_target, pan=pan, tilt=tilt)
    if method in _CV_METHODS:
        H = _as_poses(base_T_head, "base_T_head")
        check_excitation(H, pan, tilt)
        return solve_opencv(H, cam_T_target, method)
    raise ValueError(f"unknown method {method!r} (choose from {', '.join(METHODS)})")
