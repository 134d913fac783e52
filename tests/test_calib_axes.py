"""Pan/tilt axis calibration (calib/axes.py): lines from motions, common perpendicular."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cgamap.calib.axes import (
    AxisCalibrationError,
    calibrate_axes,
    common_perpendicular,
    joint_motor,
    screw_axis,
    screw_line,
)
from cgamap.calib.collect import pose_set
from cgamap.calib.se3 import inv, make_pose, perturb, so3_exp
from cgamap.calib.sim import default_rig
from cgamap.cga import apply_points, motor_to_matrix


def test_joint_motor_turns_about_its_line():
    p, d = np.array([1.0, 2.0, 0.5]), np.array([0.0, 0.0, 1.0])
    M = joint_motor(p, d, np.array(math.pi / 2))
    # Points on the line stay; a point 1 m off it (in +x) goes to +y (right-handed about z).
    np.testing.assert_allclose(apply_points(M, p + 0.3 * d), p + 0.3 * d, atol=1e-12)
    np.testing.assert_allclose(apply_points(M, p + [1.0, 0, 0]), p + [0, 1.0, 0], atol=1e-12)


def _skewed_head(non_orth_deg, offset, n=20, seed=0, noise=None):
    """Camera poses of a head whose tilt axis is off by ``non_orth_deg`` and passes
    ``offset`` metres from the pan axis: T = S_pan(pan) S_tilt(tilt) T0 (target frame)."""
    rng = np.random.default_rng(seed)
    p1, d1 = np.array([0.1, -0.2, -1.0]), np.array([0.0, -1.0, 0.0])
    d2 = so3_exp(np.array([0.0, 0.0, np.radians(non_orth_deg)])) @ np.array([1.0, 0.0, 0.0])
    p2 = p1 + offset * np.cross(d1, d2) / np.linalg.norm(np.cross(d1, d2))
    T0 = make_pose(so3_exp(rng.normal(scale=0.1, size=3)), p1 + [0.05, 0.05, 0.0])
    q = pose_set(n, math.radians(12), math.radians(8))
    T = motor_to_matrix(joint_motor(p1, d1, q[:, 0]) * joint_motor(p2, d2, q[:, 1])) @ T0
    C = inv(T)
    if noise:
        C = perturb(C, rng, *noise)
    return C, q, (p1, d1, p2, d2)


@pytest.mark.parametrize("non_orth,offset", [(0.0, 0.0), (1.5, 0.004), (-0.7, 0.012)])
def test_axes_exact_noise_free(non_orth, offset):
    C, q, (p1, d1, p2, d2) = _skewed_head(non_orth, offset)
    ax = calibrate_axes(C, q[:, 0], q[:, 1])
    assert ax.frame == "target"
    assert abs(ax.non_orthogonality_deg - non_orth) < 1e-6
    assert abs(ax.offset_m - offset) < 1e-7
    assert abs(abs(ax.pan_direction @ d1) - 1) < 1e-10
    c1, c2 = common_perpendicular(p1, d1, p2, d2)
    np.testing.assert_allclose(ax.axis_point, 0.5 * (c1 + c2), atol=1e-7)
    L_pan, L_tilt = ax.lines()  # CGA lines carry the same axes
    assert L_pan.shape == () and L_tilt.shape == ()


def test_axes_with_pose_noise():
    C, q, _ = _skewed_head(1.0, 0.005, n=30, noise=(np.radians(0.05), 0.0003))
    ax = calibrate_axes(C, q[:, 0], q[:, 1])
    assert abs(ax.non_orthogonality_deg - 1.0) < 0.3
    assert abs(ax.offset_m - 0.005) < 0.002


def test_axes_in_the_base_frame_on_the_sim_rig():
    rig = default_rig(2)
    q = pose_set(20, math.radians(12), math.radians(8))
    C = np.array([rig.cam_T_target(p, t) for p, t in q])
    ax = calibrate_axes(C, q[:, 0], q[:, 1], base_T_target=rig.base_T_target)
    assert ax.frame == "base"
    np.testing.assert_allclose(ax.axis_point, rig.axis_point, atol=1e-8)
    np.testing.assert_allclose(ax.pan_direction, [0, 0, 1], atol=1e-9)
    assert abs(ax.non_orthogonality_deg) < 1e-7


def test_axes_refuse_a_still_joint():
    C, q, _ = _skewed_head(0.0, 0.0)
    with pytest.raises(AxisCalibrationError, match="tilt joint"):
        calibrate_axes(C, q[:, 0], np.zeros(len(q)))
    with pytest.raises(AxisCalibrationError, match="parallel"):
        common_perpendicular(np.zeros(3), np.array([0, 0, 1.0]), np.ones(3),
                             np.array([0, 0, 1.0]))


def test_screw_axis_of_a_joint_motion_is_its_line():
    p, d = np.array([0.3, -0.1, 2.0]), np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1, 2, -0.5])
    T = motor_to_matrix(joint_motor(p, d, np.array(0.7)))
    T[:3, 3] += 0.05 * d  # plus a slide along the axis: a screw
    q, e, angle, slide = screw_axis(T)
    np.testing.assert_allclose(e, d, atol=1e-12)
    assert abs(angle - 0.7) < 1e-12 and abs(slide - 0.05) < 1e-12
    assert np.linalg.norm(np.cross(q - p, d)) < 1e-12  # q lies on the line
    assert abs(q @ d) < 1e-12  # and is its point closest to the origin
    L = screw_line(T)
    from cgamap.cga import line_point_direction

    q2, e2 = line_point_direction(L)
    np.testing.assert_allclose(q2, q, atol=1e-12)
    np.testing.assert_allclose(e2, d, atol=1e-12)
