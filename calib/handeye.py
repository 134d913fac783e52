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
2. Refinement: least squares over X and the target pose Y = base_T_target together on the
   absolute residuals Y^-1 H_i X C_i (each pose pair's noise enters once, not in every motion
   that uses it), whitened by rotation and translation scales estimated from the data, with a
   Huber loss by iteratively reweighting; pose pairs beyond the chi-square gate are rejected
   and the fit repeated.
3. Uncertainty: the covariance of X at the optimum in the sandwich (cluster-robust) form
   A^-1 B A^-1, A the Gauss-Newton normal matrix and B the outer products of each pose pair's
   score, so that it holds when the noise model is only approximate (measured: on the rendered
   target pipeline the model-based form overstates the rotation spread about 4x, the sandwich
   is within 25 %); the model-based one is kept in ``info``.

Degenerate input (all rotations about one axis leave X free to turn about it and slide along
it) is refused before solving, naming the missing excitation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from cgamap.cga import Multivector, blade_index, motor_from_matrix, motor_to_matrix

from .se3 import inv, make_pose, project_rotation, skew, so3_exp, so3_log

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


@dataclass
class HandEyeResult:
    """A hand-eye solution: the mount, the target pose, residuals and uncertainty."""

    head_T_cam: np.ndarray  # (4, 4)
    method: str
    base_T_target: np.ndarray | None = None
    inliers: np.ndarray | None = None  # (n,) bool: pose pairs kept
    residual_rot_deg: np.ndarray | None = None  # (n,) per pose pair, against the solution
    residual_trans_m: np.ndarray | None = None
    sigma_rot_deg: float | None = None  # estimated noise scale per axis
    sigma_trans_m: float | None = None
    std_rot_deg: np.ndarray | None = None  # (3,) 1-sigma of the mount rotation (head frame)
    std_trans_m: np.ndarray | None = None  # (3,) 1-sigma of the mount translation
    covariance: np.ndarray | None = None  # (6, 6): rotation vector (rad), translation (m)
    linear: np.ndarray | None = None  # the linear (motor SVD) estimate before refinement
    info: dict = field(default_factory=dict)


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


# ---- 2. refinement on the absolute residuals ----------------------------------------------

def _residuals(X: np.ndarray, Y: np.ndarray, H: np.ndarray, C: np.ndarray):
    """Residuals (n, 6) of Z_i = H_i X C_i against Y in the base frame: the rotation vector
    of R_Z R_Y^T and t_Z - t_Y.  Also returns Z."""
    Z = H @ X @ C
    rot = so3_log(Z[:, :3, :3] @ Y[:3, :3].T)
    return np.concatenate([rot, Z[:, :3, 3] - Y[:3, 3]], axis=-1), Z


def _jl_inv(e: np.ndarray) -> np.ndarray:
    """Inverse left Jacobian of SO(3) at rotation vectors e (..., 3)."""
    th = np.linalg.norm(e, axis=-1)[..., None, None]
    K = skew(e)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0,
                 1.0 / ths**2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(ths)))
    return np.eye(3) - 0.5 * K + c * (K @ K)


def _jacobian(X, Y, H, C) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (n, 6) and their analytic Jacobian (n, 6, 12) for the parameters of
    ``_perturbed``: d rot = Jl^-1(e) (R_H w_X - w_Y), d t = R_H (v_X - [R_X t_C]x w_X) - v_Y."""
    res, _ = _residuals(X, Y, H, C)
    n = len(H)
    RH = H[:, :3, :3]
    J = np.zeros((n, 6, 12))
    Jl = _jl_inv(res[:, :3])
    J[:, :3, 0:3] = Jl @ RH
    J[:, :3, 6:9] = -_jl_inv(-res[:, :3])  # right Jacobian: R_Y^T gains exp(-w_Y)
    lever = np.einsum("ij,nj->ni", X[:3, :3], C[:, :3, 3])
    J[:, 3:, 0:3] = -RH @ skew(lever)
    J[:, 3:, 3:6] = RH
    J[:, 3:, 9:12] = -np.eye(3)
    return res, J


def _perturbed(X: np.ndarray, Y: np.ndarray, p: np.ndarray):
    """X and Y moved by a parameter vector p (12,): left rotation vector and translation
    offset of X (head frame), then of Y (base frame)."""
    Xp = make_pose(so3_exp(p[0:3]) @ X[:3, :3], X[:3, 3] + p[3:6])
    Yp = make_pose(so3_exp(p[6:9]) @ Y[:3, :3], Y[:3, 3] + p[9:12])
    return Xp, Yp


def _mean_pose(Z: np.ndarray) -> np.ndarray:
    return make_pose(project_rotation(Z[:, :3, :3].sum(0)), Z[:, :3, 3].mean(0))


_CHI2_3_MEDIAN = 2.365973884375338  # median of chi-square with 3 degrees of freedom


class _NoiseModel:
    """Per-pair whitening of the residuals r_i = (rotation vector, translation) of
    Z_i = H_i X C_i against Y, in the base frame.

    The head pose carries rotation noise (variance h per axis) and translation noise; the
    camera's target pose carries its own.  The head's rotation noise also moves the target
    estimate by the lever arm L_i = t_Z - t_H, so the residual covariance is
    [[a I, h [L]x], [h [L]x^T, b I + h [L]x [L]x^T]] with a = total rotation variance,
    b = total translation variance, h = f a the head's share of a (0 <= f <= 1): f = 0 is a
    precise head (all noise in the camera), f = 1/2 equal noise on both.  ``lever=False``
    fixes f = 0.  a, b and f are estimated from the residuals by a robust maximum
    likelihood (``estimate``)."""

    def __init__(self, floor_rot: float, floor_trans: float, lever: bool = True):
        self.floor_rot, self.floor_trans, self.lever = floor_rot, floor_trans, lever
        self.a = self.b = 1.0
        self.f = 0.5 if lever else 0.0

    @property
    def sr(self) -> float:
        """Rotation noise per axis and per measured pose, shared equally (rad)."""
        return float(np.sqrt(self.a / 2))

    @property
    def st(self) -> float:
        return float(np.sqrt(self.b / 2))

    def estimate(self, res: np.ndarray, L: np.ndarray, gate: float = 22.46) -> None:
        """Robust maximum likelihood: minimise sum_i rho(d_i^2) + log det Sigma_i over
        (log a, log b, f) on a coarse then finer grids around the median-based first guess;
        rho is quadratic up to ``gate`` and grows as the square root beyond (Huber), so gross
        outliers do not inflate the scales (a hard cap would let them shrink to 0).

        Closed forms by the Schur complement of the rotation block: with
        u = r_t + f L x r_r, d^2 = |r_r|^2 / a + (u.l)^2 / b + |u_perp|^2 / (b + f(1-f) a |L|^2)
        for l = L / |L|, and log det = 3 log a + log b + 2 log(b + f(1-f) a |L|^2)."""
        rr2 = np.sum(res[:, :3] ** 2, -1)
        rt = res[:, 3:]
        a0 = max(np.median(rr2) / _CHI2_3_MEDIAN, self.floor_rot**2)
        b0 = max(np.median(np.sum(rt**2, -1)) / _CHI2_3_MEDIAN, self.floor_trans**2)
        L2 = np.sum(L**2, -1)
        lhat = L / np.sqrt(np.where(L2 > 0, L2, 1.0))[:, None]
        c = np.cross(L, res[:, :3])  # perpendicular to L
        t_par2 = np.einsum("ni,ni->n", rt, lhat) ** 2
        t2, tc, c2 = np.sum(rt**2, -1), np.einsum("ni,ni->n", rt, c), np.sum(c**2, -1)
        la, lb, f = np.log(a0), np.log(b0), self.f if self.lever else 0.0
        for span, steps, fspan in ((4.0, 17, 0.5), (0.6, 13, 0.15), (0.1, 11, 0.03)):
            ga = la + np.linspace(-span, span, steps)
            gb = lb + np.linspace(-span, span, steps)
            gf = (np.clip(f + np.linspace(-fspan, fspan, 11), 0.0, 1.0) if self.lever
                  else np.zeros(1))
            A = np.exp(ga)[:, None, None, None]
            B = np.exp(gb)[None, :, None, None]
            F = gf[None, None, :, None]
            perp = B + F * (1 - F) * A * L2
            uperp2 = t2 + 2 * F * tc + F**2 * c2 - t_par2
            d2 = rr2 / A + t_par2 / B + uperp2 / perp
            logdet = 3 * np.log(A) + np.log(B) + 2 * np.log(perp)
            rho = np.where(d2 <= gate, d2, 2.0 * np.sqrt(gate * d2) - gate)
            nll = np.sum(rho + logdet, -1)
            i, j, k = np.unravel_index(np.argmin(nll), nll.shape)
            la, lb, f = ga[i], gb[j], float(gf[k])
        self.a = max(np.exp(la), 2 * self.floor_rot**2)
        self.b = max(np.exp(lb), 2 * self.floor_trans**2)
        self.f = f

    def covariances(self, L: np.ndarray) -> np.ndarray:
        """(n, 6, 6) residual covariances."""
        n = len(L)
        h = self.f * self.a
        K = skew(L)
        S = np.zeros((n, 6, 6))
        S[:, :3, :3] = self.a * np.eye(3)
        S[:, :3, 3:] = h * K
        S[:, 3:, :3] = h * np.swapaxes(K, -1, -2)
        S[:, 3:, 3:] = self.b * np.eye(3) + h * (K @ np.swapaxes(K, -1, -2))
        return S

    def whiteners(self, L: np.ndarray) -> np.ndarray:
        """(n, 6, 6) W_i with W_i^T W_i = Sigma_i^-1."""
        return np.linalg.inv(np.linalg.cholesky(self.covariances(L)))


def _lever(H: np.ndarray, Z: np.ndarray) -> np.ndarray:
    return Z[:, :3, 3] - H[:, :3, 3]


def _gauss_newton(X, Y, H, C, W, weights, iters: int = 30):
    """Levenberg-Marquardt on sum_i w_i |W_i r_i|^2 over X and Y."""
    lam = 1e-6
    sw = np.sqrt(weights)[:, None]
    res, J = _jacobian(X, Y, H, C)
    cost = np.sum(weights * np.sum(np.einsum("nij,nj->ni", W, res) ** 2, -1))
    for _ in range(iters):
        Jw = (sw[:, :, None] * (W @ J)).reshape(-1, 12)
        rw = (sw * np.einsum("nij,nj->ni", W, res)).reshape(-1)
        JtJ, g = Jw.T @ Jw, Jw.T @ rw
        improved = False
        for _ in range(8):
            step = -np.linalg.solve(JtJ + lam * np.diag(np.diag(JtJ) + 1e-12), g)
            Xn, Yn = _perturbed(X, Y, step)
            res_n, _ = _residuals(Xn, Yn, H, C)
            cost_n = np.sum(weights * np.sum(np.einsum("nij,nj->ni", W, res_n) ** 2, -1))
            if cost_n <= cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        X, Y, lam = Xn, Yn, max(lam / 10.0, 1e-9)
        done = cost - cost_n <= 1e-12 * max(cost, 1e-300) or np.max(np.abs(step)) < 1e-13
        cost = cost_n
        res, J = _jacobian(X, Y, H, C)
        if done:
            break
    return X, Y, res, J


def refine(H: np.ndarray, C: np.ndarray, X0: np.ndarray, *, huber: float = 3.0,
           gate_chi2: float = 22.46, floor_rot: float = 1e-7, floor_trans: float = 1e-7,
           max_reject: float = 0.34, keep0: np.ndarray | None = None,
           lever: bool = True) -> HandEyeResult:
    """Robust least-squares refinement of X = head_T_cam (and Y = base_T_target).

    Huber IRLS on the whitened per-pair residual norm, noise scales re-estimated each round;
    pose pairs whose whitened squared residual exceeds ``gate_chi2`` (chi-square, 6 dof,
    99.9 %) are rejected (at most ``max_reject`` of them) and the fit repeated."""
    n = len(H)
    keep = np.ones(n, bool) if keep0 is None else keep0.copy()
    min_keep = max(3, int(np.ceil((1 - max_reject) * n)))
    noise = _NoiseModel(floor_rot, floor_trans, lever)
    X = X0.copy()
    for _ in range(4):  # rejection rounds
        Hk, Ck = H[keep], C[keep]
        Y = _mean_pose(Hk @ X @ Ck)
        weights = np.ones(keep.sum())
        res, Z = _residuals(X, Y, Hk, Ck)
        noise.estimate(res, _lever(Hk, Z))
        for _ in range(3):  # IRLS rounds
            W = noise.whiteners(_lever(Hk, Z))
            X, Y, res, _ = _gauss_newton(X, Y, Hk, Ck, W, weights)
            res, Z = _residuals(X, Y, Hk, Ck)
            noise.estimate(res, _lever(Hk, Z))
            norm = np.linalg.norm(np.einsum("nij,nj->ni", noise.whiteners(_lever(Hk, Z)), res),
                                  axis=-1)
            new_w = np.where(norm <= huber * np.sqrt(6), 1.0, huber * np.sqrt(6) / norm)
            if np.allclose(new_w, weights, atol=1e-3):
                break
            weights = new_w
        # Gate every pose pair (rejected ones may come back) against the current solution.
        res_all, Z_all = _residuals(X, Y, H, C)
        white = np.einsum("nij,nj->ni", noise.whiteners(_lever(H, Z_all)), res_all)
        chi2 = np.sum(white**2, -1)
        new_keep = chi2 <= gate_chi2
        if new_keep.sum() < min_keep:
            new_keep = np.zeros(n, bool)
            new_keep[np.argsort(chi2)[:min_keep]] = True
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    # Final fit on the inliers with plain least squares.
    Hk, Ck = H[keep], C[keep]
    res, Z = _residuals(X, Y, Hk, Ck)
    W = noise.whiteners(_lever(Hk, Z))
    X, Y, res, J = _gauss_newton(X, Y, Hk, Ck, W, np.ones(keep.sum()))
    Jw = (W @ J).reshape(-1, 12)
    dof = max(6 * keep.sum() - 12, 1)
    chi2_red = float(np.sum(np.einsum("nij,nj->ni", W, res) ** 2) / dof)
    try:
        Ainv = np.linalg.inv(Jw.T @ Jw)
        cov_model = Ainv * chi2_red
        # Sandwich (cluster-robust) form: the scores of each pose pair taken as observed, so
        # a noise model that misses the camera's anisotropy does not misstate the spread.
        g = np.einsum("nki,nk->ni", (W @ J), np.einsum("nij,nj->ni", W, res))
        m = len(g)
        cov_sandwich = Ainv @ (g.T @ g) @ Ainv * (m / max(m - 12 / 6, 1))
    except np.linalg.LinAlgError:
        cov_model = cov_sandwich = np.full((12, 12), np.nan)
    cov = cov_sandwich
    res_all, _ = _residuals(X, Y, H, C)
    out = HandEyeResult(
        head_T_cam=X, method="motor", base_T_target=Y, inliers=keep,
        residual_rot_deg=np.degrees(np.linalg.norm(res_all[:, :3], axis=-1)),
        residual_trans_m=np.linalg.norm(res_all[:, 3:], axis=-1),
        sigma_rot_deg=float(np.degrees(noise.sr)), sigma_trans_m=noise.st,
        covariance=cov[:6, :6],
        std_rot_deg=np.degrees(np.sqrt(np.abs(np.diag(cov)[:3]))),
        std_trans_m=np.sqrt(np.abs(np.diag(cov)[3:6])),
    )
    out.info["chi2_reduced"] = chi2_red
    out.info["std_rot_deg_model"] = np.degrees(np.sqrt(np.abs(np.diag(cov_model)[:3])))
    out.info["std_trans_m_model"] = np.sqrt(np.abs(np.diag(cov_model)[3:6]))
    out.info["head_noise_share"] = noise.f
    return out


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
    res, _ = _residuals(X, _mean_pose(H @ X @ C), H, C)
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
