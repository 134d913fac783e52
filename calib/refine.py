"""Refinement of a hand-eye solution on the absolute residuals, and its uncertainty.

Least squares over X = head_T_cam and the target pose Y = base_T_target together on
r_i = (Y^-1 H_i X C_i as rotation vector and translation, in the base frame): each pose pair's
noise enters once, not in every motion that uses it.  The residuals are whitened per pair by a
noise model whose scales (and the head's share of the rotation noise, which acts through the
lever arm to the target) come from the data by a robust maximum likelihood; a Huber loss by
iteratively reweighting; pose pairs beyond the chi-square gate are rejected and the fit
repeated.  The covariance of X is given in the sandwich (cluster-robust) form A^-1 B A^-1,
A the Gauss-Newton normal matrix and B the outer products of each pose pair's score, so that it
holds when the noise model is only approximate (measured: on the rendered-target pipeline the
model-based form overstates the rotation spread about 4x, the sandwich is within 25 %); the
model-based one is kept in ``info``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .se3 import make_pose, project_rotation, skew, so3_exp, so3_log


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


def residuals(X: np.ndarray, Y: np.ndarray, H: np.ndarray, C: np.ndarray):
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
    res, _ = residuals(X, Y, H, C)
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


def mean_pose(Z: np.ndarray) -> np.ndarray:
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
            res_n, _ = residuals(Xn, Yn, H, C)
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
        Y = mean_pose(Hk @ X @ Ck)
        weights = np.ones(keep.sum())
        res, Z = residuals(X, Y, Hk, Ck)
        noise.estimate(res, _lever(Hk, Z))
        for _ in range(3):  # IRLS rounds
            W = noise.whiteners(_lever(Hk, Z))
            X, Y, res, _ = _gauss_newton(X, Y, Hk, Ck, W, weights)
            res, Z = residuals(X, Y, Hk, Ck)
            noise.estimate(res, _lever(Hk, Z))
            norm = np.linalg.norm(np.einsum("nij,nj->ni", noise.whiteners(_lever(Hk, Z)), res),
                                  axis=-1)
            new_w = np.where(norm <= huber * np.sqrt(6), 1.0, huber * np.sqrt(6) / norm)
            if np.allclose(new_w, weights, atol=1e-3):
                break
            weights = new_w
        # Gate every pose pair (rejected ones may come back) against the current solution.
        res_all, Z_all = residuals(X, Y, H, C)
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
    res, Z = residuals(X, Y, Hk, Ck)
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
    res_all, _ = residuals(X, Y, H, C)
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
