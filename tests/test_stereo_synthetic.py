"""The stereo twin: rendering the 3D world, SGBM + reprojection against ground truth."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.drivers.sim.stereo_render import (
    SyntheticGrabber,
    default_calibration,
    render_pair,
    value_noise,
)
from cgamap.drivers.sim.world3d import SceneBuilder, get_scene
from cgamap.drivers.stereo import frame_points, frame_points_global, open_grabber
from cgamap.drivers.stereo_points import camera_motor, points_to_global


@pytest.fixture(scope="module")
def corridor_frame():
    # Robot at x = 3 m on the corridor's axis, looking down it; head tilted 0.2 rad down.
    g = SyntheticGrabber("corridor", pose=(3.0, 0.0, 0.0), tilt=0.2, seed=1)
    return g, g.grab()


def test_raycast_hits_known_planes():
    scene = SceneBuilder().floor(-5, -5, 5, 5).quad((2, -1, 0), (0, 2, 0), (0, 0, 2), "wall") \
        .build("t")
    dirs = np.array([[1.0, 0, 0], [1.0, 0, -0.5], [-1.0, 0, 0], [1.0, 0.9, 0]])
    t, idx, a, b = scene.raycast(np.array([0.0, 0.0, 1.0]), dirs)
    assert t[0] == pytest.approx(2.0) and idx[0] == 1          # the wall, 2 m ahead
    assert a[0] == pytest.approx(1.0) and b[0] == pytest.approx(1.0)
    assert t[1] == pytest.approx(2.0) and idx[1] == 0          # floor at x = 2 (z = 0)
    assert idx[2] == -1 and np.isinf(t[2])                     # nothing behind
    assert idx[3] == -1                                        # passes beside the wall
    n, rho = scene.planes()
    assert np.allclose(np.abs(n[1]), [1, 0, 0]) and rho[1] == pytest.approx(2.0)


def test_texture_is_deterministic_and_varied():
    a = np.linspace(0, 1, 200)
    v1 = value_noise(a, a * 0.3, np.full(200, 5), 0.05)
    v2 = value_noise(a, a * 0.3, np.full(200, 5), 0.05)
    v3 = value_noise(a, a * 0.3, np.full(200, 6), 0.05)
    assert np.array_equal(v1, v2) and not np.allclose(v1, v3)
    assert v1.std() > 0.1 and 0 <= v1.min() and v1.max() < 1


def test_rendered_depth_is_exact_for_a_wall():
    scene = SceneBuilder().quad((3, -5, -5), (0, 10, 0), (0, 0, 10), "wall").build("w")
    calib = default_calibration((160, 100), fx=120.0)
    M = camera_motor((0.0, 0.0, 0.0), 0.0, 0.0)  # looking along +x from (0, 0, 0.5)
    left, right, depth = render_pair(scene, M, calib, (160, 100))
    assert left.shape == (100, 160) and left.dtype == np.uint8
    assert np.nanmax(np.abs(depth - 3.0)) < 1e-9   # a fronto-parallel wall: z = 3 everywhere
    assert left.std() > 10 and not np.array_equal(left, right)


def test_corridor_walls_recovered_from_sgbm(corridor_frame):
    g, f = corridor_frame
    assert f.ground_truth is not None and f.disparity is not None
    assert f.pose_ref == (3.0, 0.0, 0.0) and f.pantilt.tilt == pytest.approx(0.2)
    depth = f.depth_image()
    ok = np.isfinite(depth) & np.isfinite(f.ground_truth)
    assert ok.mean() > 0.6
    rel = np.abs(depth - f.ground_truth)[ok] / f.ground_truth[ok]
    print(f"synthetic corridor: density {ok.mean():.2f}, median rel. depth error "
          f"{np.median(rel):.4f}")
    assert np.median(rel) < 0.02
    pts = frame_points_global(f, g.mount, max_depth=6.0)
    # Walls at y = -1 and y = +1 (away from the niche at x 6..7), floor at z = 0.
    span = (pts[:, 0] > 3.5) & (pts[:, 0] < 5.8) & (pts[:, 2] > 0.2) & (pts[:, 2] < 2.0)
    right_wall = pts[span & (pts[:, 1] < -0.8) & (pts[:, 1] > -1.2), 1]
    left_wall = pts[span & (pts[:, 1] > 0.8) & (pts[:, 1] < 1.2), 1]
    floor = pts[(np.abs(pts[:, 2]) < 0.2) & (np.abs(pts[:, 1]) < 0.8) & (pts[:, 0] < 7.0), 2]
    assert len(right_wall) > 2000 and len(left_wall) > 2000 and len(floor) > 2000
    errs = (abs(np.median(right_wall) + 1.0), abs(np.median(left_wall) - 1.0),
            abs(np.median(floor)))
    print(f"wall/floor offsets (m): {np.round(errs, 4)}")
    assert max(errs) < 0.03
    # Least-squares planes through the selected points: within 2 degrees of the truth.
    for sel, normal in ((span & (pts[:, 1] < -0.8) & (pts[:, 1] > -1.2), (0, 1, 0)),
                        (span & (pts[:, 1] > 0.8) & (pts[:, 1] < 1.2), (0, 1, 0)),
                        ((np.abs(pts[:, 2]) < 0.2) & (np.abs(pts[:, 1]) < 0.8), (0, 0, 1))):
        q = pts[sel]
        fit = np.linalg.svd(q - q.mean(0), full_matrices=False)[2][2]
        angle = np.degrees(np.arccos(min(1.0, abs(fit @ np.array(normal, float)))))
        assert angle < 2.0, angle


def test_global_points_match_true_depth_points(corridor_frame):
    # The same chain applied to ground-truth depth puts points exactly on the planes.
    g, f = corridor_frame
    from cgamap.drivers.stereo_points import depth_to_points

    pts_c = depth_to_points(f.ground_truth, f.calib, max_depth=6.0, stride=4)
    pts = points_to_global(pts_c, camera_motor(f.pose_ref, 0.0, 0.2, g.mount))
    n, rho = g.scene.planes()
    dist = np.min(np.abs(pts @ n.T - rho), axis=1)
    assert np.max(dist) < 1e-6


def test_stairs_scene_and_open_grabber():
    scene = get_scene("stairs")
    n, rho = scene.planes()
    treads = [k for k in scene.kinds if k == "tread"]
    assert len(treads) == 6
    horiz = np.isclose(np.abs(n[:, 2]), 1.0)
    heights = np.sort(rho[horiz & np.array([k == "tread" for k in scene.kinds])])
    assert np.allclose(np.diff(heights), 0.17)
    g = open_grabber("synthetic", "stairs", {"size": (320, 200), "fx": 225.0,
                                             "pose": (17.5, 0.0, 0.0), "tilt": 0.3})
    with g:
        frames = list(g.frames(count=2))
    assert [f.seq for f in frames] == [0, 1]
    assert frames[0].left.shape == (200, 320)
    assert len(frame_points(frames[0])) > 10_000


def test_trajectory_frames_move():
    g = SyntheticGrabber("room", size=(160, 100), fx=112.5, fps=1.0)
    f0, f1 = g.grab(), g.grab()
    assert f0.pose_ref != f1.pose_ref and f1.stamp_ns >= f0.stamp_ns
    assert f1.meta["sim_time"] == pytest.approx(1.0)


def test_raw_rig_rectified_end_to_end():
    """A distorted, slightly rotated rig rendered raw; rectified with its calibration, matched,
    reprojected (rectifying rotation undone) and carried to the world: points on the walls."""
    import cv2
    from cgamap.cga import motor_to_matrix
    from cgamap.drivers.sim.stereo_render import render_raw_pair
    from cgamap.drivers.stereo import sgbm_frame
    from cgamap.drivers.stereo_calib import from_raw
    from cgamap.drivers.stereo_points import CameraMount
    from cgamap.drivers.stereo_sgbm import SgbmParams

    size = (480, 300)
    K1 = np.array([[330.0, 0, 236.0], [0, 328.0, 152.0], [0, 0, 1]])
    K2 = np.array([[332.0, 0, 242.0], [0, 331.0, 147.0], [0, 0, 1]])
    D1 = np.array([-0.08, 0.02, 0.001, -0.001, 0.0])
    D2 = np.array([-0.06, 0.01, 0.0, 0.001, 0.0])
    R = cv2.Rodrigues(np.array([0.01, 0.04, 0.015]))[0]   # about 2.5 degrees off parallel
    T = np.array([-0.12, 0.002, 0.003])
    mount = CameraMount(t_axis=(0.1, 0.0, 1.0), t_eye=(0.05, 0.06, 0.05))
    M = camera_motor((3.0, 0.0, 0.0), 0.0, 0.2, mount)
    scene = get_scene("corridor")
    left, right, _ = render_raw_pair(scene, motor_to_matrix(M), K1, D1, K2, D2, R, T, size)
    calib = from_raw(K1, D1, K2, D2, R, T, size)
    f = sgbm_frame(0, 0, left, right, calib, SgbmParams(num_disparities=64))
    pts = points_to_global(frame_points(f, max_depth=6.0), M)
    n, rho = scene.planes()
    dist = np.min(np.abs(pts @ n.T - rho), axis=1)
    print(f"raw rig: {len(pts)} points, plane distance median {np.median(dist):.4f} m, "
          f"p80 {np.percentile(dist, 80):.4f} m")
    assert len(pts) > 40_000
    assert np.median(dist) < 0.015 and np.percentile(dist, 80) < 0.04
    # Without undoing the rectifying rotation the points would miss the walls.
    f.calib.R_rect, R1 = None, f.calib.R_rect
    pts_bad = points_to_global(frame_points(f, max_depth=6.0), M)
    bad = np.median(np.min(np.abs(pts_bad @ n.T - rho), axis=1))
    print(f"without R_rect: median {bad:.4f} m")
    assert bad > np.median(dist) * 1.5
    f.calib.R_rect = R1


@pytest.mark.parametrize("world,pose,tilt", [("corridor", (3.0, 0.0, 0.0), 0.2),
                                             ("stairs", (17.0, 0.0, 0.3), 0.15),
                                             ("room", (1.2, 1.2, 0.5), 0.3)])
def test_pinhole_fast_path_equals_general_raycast(world, pose, tilt):
    from cgamap.cga import motor_to_matrix
    from cgamap.drivers.sim.stereo_render import _pixel_rays, _raycast_pinhole

    g = SyntheticGrabber(world, size=(320, 200), fx=225.0, pose=pose, tilt=tilt)
    H = motor_to_matrix(g.camera_motor_at(0.0)[0])
    c = g.calib
    dirs = _pixel_rays(c.fx, c.fy, c.cx, c.cy, 320, 200) @ H[:3, :3].T
    t1, i1, a1, b1 = g.scene.raycast(H[:3, 3], dirs)
    t2, i2, a2, b2 = _raycast_pinhole(g.scene, H[:3, 3], H[:3, :3], c, 320, 200, dirs)
    assert np.array_equal(i1, i2) and (i1 >= 0).mean() > 0.5
    hit = i1 >= 0
    assert np.allclose(t1[hit], t2[hit]) and np.allclose(a1[hit], a2[hit])
    assert np.allclose(b1[hit], b2[hit])


def test_unknown_scene_lists_the_3d_scenes_too():
    with pytest.raises(ValueError, match="unknown world 'nope'") as ei:
        get_scene("nope")
    for name in ("corridor", "room", "loop", "stairs", "corridor-boxes"):
        assert name in str(ei.value)
