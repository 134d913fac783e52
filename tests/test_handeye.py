"""Hand-eye solver (calib/handeye.py): exactness, order invariance, outliers, degeneracy."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.calib import handeye as he
from cgamap.calib.se3 import inv, make_pose, pose_errors, so3_exp, so3_log
from cgamap.calib.synthetic import make_problem
from cgamap.cga import motor_from_matrix, motor_to_matrix
from hypothesis import given, settings
from hypothesis import strategies as st


def _problem(seed=0, **kw):
    return make_problem(np.random.default_rng(seed), **kw)


def test_motor_conversion_is_a_homomorphism():
    # The linear step relies on motor(A) motor(X) = +/- motor(A X).
    p = _problem(1, n=3)
    A, X = p.base_T_head[0], p.head_T_cam
    lhs = motor_from_matrix(A) * motor_from_matrix(X)
    np.testing.assert_allclose(motor_to_matrix(lhs), A @ X, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_noise_free_gives_the_exact_mount(seed):
    p = _problem(seed, n=8)
    X_lin = he.solve_linear(p.base_T_head, p.cam_T_target)
    np.testing.assert_allclose(X_lin, p.head_T_cam, atol=1e-9)
    r = he.solve(p.base_T_head, p.cam_T_target)
    np.testing.assert_allclose(r.head_T_cam, p.head_T_cam, atol=1e-9)
    np.testing.assert_allclose(r.base_T_target, p.base_T_target, atol=1e-9)
    assert r.inliers.all()


def test_three_poses_suffice_noise_free():
    p = _problem(3, n=3)
    r = he.solve(p.base_T_head, p.cam_T_target)
    np.testing.assert_allclose(r.head_T_cam, p.head_T_cam, atol=1e-9)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), perm_seed=st.integers(0, 10_000))
def test_invariant_to_pair_order(seed, perm_seed):
    p = _problem(seed, n=12, sigma_rot_deg=0.2, sigma_trans_m=0.002)
    perm = np.random.default_rng(perm_seed).permutation(12)
    a = he.solve(p.base_T_head, p.cam_T_target)
    b = he.solve(p.base_T_head[perm], p.cam_T_target[perm])
    np.testing.assert_allclose(a.head_T_cam, b.head_T_cam, atol=1e-9)
    np.testing.assert_array_equal(a.inliers[perm], b.inliers)


def test_noisy_solution_is_close_and_uncertainty_is_plausible():
    errs, stds = [], []
    for seed in range(20):
        p = _problem(seed, n=20, sigma_rot_deg=0.1, sigma_trans_m=0.001)
        r = he.solve(p.base_T_head, p.cam_T_target)
        e_rot, e_t = pose_errors(r.head_T_cam, p.head_T_cam)
        errs.append((e_rot, e_t))
        stds.append((np.linalg.norm(r.std_rot_deg), np.linalg.norm(r.std_trans_m)))
        assert abs(r.sigma_rot_deg - 0.1) < 0.05
    errs, stds = np.array(errs), np.array(stds)
    assert np.median(errs[:, 0]) < 0.2 and np.median(errs[:, 1]) < 0.003
    # The predicted 1-sigma matches the observed RMS error within a factor of two.
    ratio_rot = np.sqrt(np.mean(errs[:, 0] ** 2)) / np.sqrt(np.mean(stds[:, 0] ** 2))
    ratio_t = np.sqrt(np.mean(errs[:, 1] ** 2)) / np.sqrt(np.mean(stds[:, 1] ** 2))
    assert 0.5 < ratio_rot < 2.0 and 0.5 < ratio_t < 2.0


def test_beats_the_linear_step_on_average():
    lin, ours = [], []
    for seed in range(15):
        p = _problem(seed, n=20, sigma_rot_deg=0.5, sigma_trans_m=0.003)
        lin.append(pose_errors(he.solve_linear(p.base_T_head, p.cam_T_target), p.head_T_cam))
        ours.append(pose_errors(he.solve(p.base_T_head, p.cam_T_target).head_T_cam,
                                p.head_T_cam))
    assert np.mean(np.array(ours)[:, 0]) < np.mean(np.array(lin)[:, 0])
    assert np.mean(np.array(ours)[:, 1]) < np.mean(np.array(lin)[:, 1])


@pytest.mark.parametrize("seed", range(4))
def test_outlier_pairs_are_rejected(seed):
    rng = np.random.default_rng(100 + seed)
    p = make_problem(rng, n=20, sigma_rot_deg=0.1, sigma_trans_m=0.001)
    C = p.cam_T_target.copy()
    bad = rng.choice(20, size=3, replace=False)
    # Gross errors: a mis-detected target (10-30 degrees off, a few centimetres away).
    for k in bad:
        w = rng.normal(size=3)
        w *= np.radians(rng.uniform(10, 30)) / np.linalg.norm(w)
        C[k] = make_pose(so3_exp(w) @ C[k, :3, :3], C[k, :3, 3] + rng.uniform(-0.05, 0.05, 3))
    r = he.solve(p.base_T_head, C)
    assert set(np.flatnonzero(~r.inliers)) == set(bad)
    e_rot, e_t = pose_errors(r.head_T_cam, p.head_T_cam)
    assert e_rot < 0.3 and e_t < 0.005
    # Without rejection the same data gives a clearly worse mount.
    naive = he.solve_linear(p.base_T_head, C)
    assert pose_errors(naive, p.head_T_cam)[0] > 2 * e_rot


def _pan_tilt_poses(pan, tilt):
    Rz = so3_exp(np.stack([np.zeros_like(pan), np.zeros_like(pan), pan], -1))
    Ry = so3_exp(np.stack([np.zeros_like(tilt), tilt, np.zeros_like(tilt)], -1))
    return make_pose(Rz @ Ry, np.array([0.1, 0.0, 0.5]))


def test_degenerate_single_axis_is_refused_naming_the_joint():
    pan = np.radians(np.linspace(-40, 40, 8))
    tilt = np.full(8, 0.2)
    H = _pan_tilt_poses(pan, tilt)
    p = _problem(0, n=3)
    Y = H[0] @ p.head_T_cam @ make_pose(np.eye(3), [0, 0, 1.0])
    C = inv(p.head_T_cam) @ inv(H) @ Y
    with pytest.raises(he.DegenerateMotionError, match="one axis.*tilt joint never moves"):
        he.solve(H, C, pan=pan, tilt=tilt)
    with pytest.raises(he.DegenerateMotionError, match="second, non-parallel axis"):
        he.solve(H, C)
    for m in ("tsai", "daniilidis"):  # OpenCV's methods are guarded the same way
        with pytest.raises(he.DegenerateMotionError):
            he.solve(H, C, method=m)
    # Moving the tilt joint too makes it solvable.
    tilt2 = np.radians(np.tile([-10.0, 15.0], 4))
    H2 = _pan_tilt_poses(pan, tilt2)
    C2 = inv(p.head_T_cam) @ inv(H2) @ Y
    r = he.solve(H2, C2, pan=pan, tilt=tilt2)
    np.testing.assert_allclose(r.head_T_cam, p.head_T_cam, atol=1e-9)


def test_no_rotation_and_too_few_pairs_are_refused():
    H = make_pose(np.eye(3), np.random.default_rng(0).uniform(-1, 1, (5, 3)))
    with pytest.raises(he.DegenerateMotionError, match="hardly rotates"):
        he.solve(H, H)
    with pytest.raises(he.DegenerateMotionError, match="at least 3"):
        he.solve(H[:2], H[:2])


def test_bad_rotation_matrix_is_named():
    p = _problem(0, n=5)
    H = p.base_T_head.copy()
    H[2, :3, :3] *= 2.0
    with pytest.raises(ValueError, match=r"base_T_head\[2\]"):
        he.solve(H, p.cam_T_target)


@pytest.mark.parametrize("method", ["tsai", "park", "horaud", "andreff", "daniilidis"])
def test_opencv_methods_agree_noise_free(method):
    p = _problem(7, n=10)
    r = he.solve(p.base_T_head, p.cam_T_target, method=method)
    e_rot, e_t = pose_errors(r.head_T_cam, p.head_T_cam)
    assert e_rot < 1e-4 and e_t < 1e-5


def test_so3_log_exp_roundtrip_near_pi():
    w = np.array([[0, 0, np.pi - 1e-9], [np.pi - 1e-4, 0, 0], [1e-12, 0, 0], [0.3, -0.2, 0.1]])
    np.testing.assert_allclose(so3_exp(so3_log(so3_exp(w))), so3_exp(w), atol=1e-8)


def test_noise_model_learns_where_the_noise_is():
    from cgamap.calib.se3 import perturb

    shares = {"camera only": [], "both": []}
    for seed in range(6):
        rng = np.random.default_rng(50 + seed)
        p = make_problem(rng, n=30)
        C = perturb(p.cam_T_target, rng, np.radians(0.2), 0.002)
        shares["camera only"].append(he.solve(p.base_T_head, C).info["head_noise_share"])
        H = perturb(p.base_T_head, rng, np.radians(0.2), 0.002)
        shares["both"].append(he.solve(H, C).info["head_noise_share"])
    assert np.median(shares["camera only"]) < 0.2
    assert 0.25 < np.median(shares["both"]) < 0.75
