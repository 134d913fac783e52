"""The 3D plane map (merging, virtual walls, exports), configurations and place recognition."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from cgamap.cga import line_point_direction, motor_from_pose, plane_to_hesse, up
from cgamap.mapping import plane_scenes as scenes
from cgamap.mapping.configurations import find_configurations
from cgamap.mapping.pcd import read_ply
from cgamap.mapping.places import PlaceDatabase, place_features
from cgamap.mapping.planemap import MapPlane, PlaneMap, polygon_gap
from cgamap.mapping.planes import PlaneParams, detect_planes, plane_error


def _within(err: tuple[float, float], deg: float, metres: float) -> bool:
    return err[0] < deg and err[1] < metres


# ---- plane map -----------------------------------------------------------------------------


def _frame_planes(pts_global, pose_t, pose_yaw, prm):
    """What a camera at (t, yaw) detects, in its own frame, and the motor to global."""
    local = scenes.rotate_z(pts_global, pose_yaw, pose_t)
    c, s = np.cos(pose_yaw / 2), np.sin(pose_yaw / 2)
    M = motor_from_pose(pose_t, np.array([c, 0.0, 0.0, s]))
    return detect_planes(local, "ransac", prm), M


def test_motor_from_pose_convention_used_here():
    """rotate_z gives frame coordinates; the motor of the same pose carries them back."""
    from cgamap.cga import apply_points

    p = np.array([[1.0, 2.0, 0.5]])
    local = scenes.rotate_z(p, 0.7, (0.3, -0.2, 0.0))
    c, s = np.cos(0.35), np.sin(0.35)
    M = motor_from_pose((0.3, -0.2, 0.0), np.array([c, 0.0, 0.0, s]))
    np.testing.assert_allclose(apply_points(M, local), p, atol=1e-12)


def test_planes_merge_across_frames_into_one_map():
    pts, truth = scenes.corridor(length=8.0, seed=11)
    prm = PlaneParams(threshold=0.015, min_inliers=400)
    pm = PlaneMap()
    # three overlapping views along the corridor, each seeing a 3 m stretch
    for x0, yaw in ((0.0, 0.0), (2.5, 0.4), (5.0, -0.3)):
        view = pts[(pts[:, 0] >= x0) & (pts[:, 0] <= x0 + 3.0)]
        planes, M = _frame_planes(view, (x0, 0.1, 0.0), yaw, prm)
        assert len(planes) == 3
        pm.add_planes(planes, M)
    assert len(pm.planes) == 3, [p.to_dict()["hough"] for p in pm.planes]
    for p in pm.planes:
        assert p.observations == 3
        assert any(_within(plane_error(p.normal, p.rho, n, r), 0.5, 0.01)
                   for n, r in truth)
        lo, hi = (p.extent @ [1.0, 0, 0]).min(), (p.extent @ [1.0, 0, 0]).max()
        assert lo < 0.1 and hi > 7.9  # the merged extent covers the whole corridor
        assert np.abs(p.corners @ p.normal - p.rho).max() < 1e-9
    # a coplanar patch far along the same wall stays a separate map plane
    far = pm.planes[0]
    shifted = MapPlane(far.normal, far.rho, far.extent + np.cross(far.normal, [0, 0, 1]) * 20,
                       inliers=100)
    pm.add_planes([shifted])
    assert len(pm.planes) == 4


def test_polygon_gap():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert polygon_gap(sq, sq + 0.5) == 0.0
    assert polygon_gap(sq, sq + [3.0, 0.0]) == pytest.approx(2.0)
    assert polygon_gap(sq, sq + [2.0, 2.0]) == pytest.approx(np.sqrt(2))


def test_virtual_walls_and_exports(tmp_path):
    pm = PlaneMap()
    segs = np.array([[[0.0, 0.0], [4.0, 0.0]], [[4.0, 0.0], [4.0, 3.0]]])
    ids = pm.add_virtual_walls(segs, height=2.4)
    assert ids == [0, 1]
    wall = pm.planes[0]
    n, rho = plane_to_hesse(wall.cga())
    assert abs(n @ [0, 1, 0]) == pytest.approx(1.0) and rho == pytest.approx(0.0, abs=1e-12)
    assert wall.kind == "wall" and wall.area == pytest.approx(4.0 * 2.4)
    # the wall's corners lie on its CGA plane
    assert np.abs((up(wall.corners) ^ wall.cga()).v).max() < 1e-9
    n1, rho1 = plane_to_hesse(pm.planes[1].cga())
    assert abs(n1 @ [1, 0, 0]) == pytest.approx(1.0) and rho1 == pytest.approx(4.0)
    pm.add_planes(detect_planes(scenes.corridor(seed=3)[0], "hough",
                                PlaneParams(threshold=0.015, min_inliers=400)))
    pm.save_ply(tmp_path / "m.ply")
    verts = read_ply(tmp_path / "m.ply")
    assert verts.shape == (4 * len(pm.planes), 3)
    text = (tmp_path / "m.ply").read_text()
    assert f"element face {len(pm.planes)}" in text and "\n4 0 1 2 3\n" in text
    pm.save_json(tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    assert [p["kind"] for p in doc["planes"]].count("wall") == 2
    assert len(doc["planes"][0]["cga"]) == 32
    again = PlaneMap()
    again.load_state(json.loads(json.dumps(pm.state())))
    assert [q["seen"] for q in again.as_list()] == [p.observations for p in pm.planes]
    assert again.integrate(pm.planes[:1]) == 1 and len(again.planes) == len(pm.planes)
    again = PlaneMap.from_dict(doc)
    assert [p.id for p in again.planes] == [p.id for p in pm.planes]
    for a, b in zip(again.planes, pm.planes, strict=True):
        np.testing.assert_allclose(a.corners, b.corners, atol=1e-4)
        assert a.kind == b.kind and a.rho == pytest.approx(b.rho, abs=1e-6)
    pm.save_hough_png(tmp_path / "h.png")
    img = cv2.imread(str(tmp_path / "h.png"))
    assert img.shape == (400, 720, 3)
    assert (img.std(axis=2) > 20).sum() > 200  # coloured discs were drawn


# ---- configurations ------------------------------------------------------------------------


def _configs(maker, prm, **kw):
    pts, truth = maker(**kw)
    planes = detect_planes(pts, "ransac", prm)
    return find_configurations(planes), planes, truth


def test_corridor_configuration_and_axis():
    found, planes, _ = _configs(scenes.corridor, PlaneParams(threshold=0.015, min_inliers=400),
                                width=2.0, seed=12)
    corr = [c for c in found if c.kind == "corridor"]
    assert len(corr) == 1 and not [c for c in found if c.kind != "corridor"]
    c = corr[0]
    assert c.params["width"] == pytest.approx(2.0, abs=0.01)
    p, d = line_point_direction(c.entities["axis"])
    assert abs(d @ [1, 0, 0]) > np.cos(np.radians(0.5))
    assert np.hypot(p[1], p[2]) < 0.01  # the axis runs along the floor midway between walls
    # too narrow or too wide: no corridor
    for width in (0.6, 5.0):
        found, _, _ = _configs(scenes.corridor, PlaneParams(threshold=0.015, min_inliers=400),
                               width=width, seed=12)
        assert not [c for c in found if c.kind == "corridor"]


def test_stairway_configuration():
    found, _, _ = _configs(scenes.stairway, PlaneParams(threshold=0.01, min_inliers=200,
                                                        max_planes=15), seed=13)
    stairs = [c for c in found if c.kind == "stairway"]
    assert len(stairs) == 1 and not [c for c in found if c.kind == "workplace"]
    s = stairs[0].params
    assert s["treads"] == 6 and s["risers"] == 5  # the floor counts as the first level
    assert s["rise"] == pytest.approx(0.17, abs=0.005)
    assert s["going"] == pytest.approx(0.28, abs=0.02)
    assert abs(np.asarray(s["direction"]) @ [1, 0, 0]) > 0.99
    # with a wider inlier band, the RANSAC normal check keeps the plane through the nosings
    # (it has more points within 2 cm than any tread) from winning
    found, _, _ = _configs(scenes.stairway, PlaneParams(threshold=0.02, min_inliers=200,
                                                        max_planes=15, normal_tol=0.3),
                           seed=13)
    stairs = [c for c in found if c.kind == "stairway"]
    assert len(stairs) == 1 and stairs[0].params["treads"] == 6
    # irregular rises are not a stairway
    pts, _ = scenes.stairway(seed=13)
    pts = pts.copy()
    pts[pts[:, 2] > 0.6, 2] += 0.08  # the top steps rise 25 cm
    planes = detect_planes(pts, "ransac", PlaneParams(threshold=0.01, min_inliers=200,
                                                      max_planes=15))
    assert not [c for c in find_configurations(planes) if c.kind == "stairway"]


def test_doorway_configuration():
    found, _, _ = _configs(scenes.doorway, PlaneParams(threshold=0.015, min_inliers=400),
                           door=0.9, seed=14)
    doors = [c for c in found if c.kind == "doorway"]
    assert len(doors) == 1
    d = doors[0]
    assert d.params["width"] == pytest.approx(0.9, abs=0.05)
    np.testing.assert_allclose(d.params["centre"], [3.0, 0.0, 0.0], atol=0.03)
    _, direction = line_point_direction(d.entities["centre_line"])
    assert abs(direction[2]) == pytest.approx(1.0)
    # a 3.5 m gap is not a door
    found, _, _ = _configs(scenes.doorway, PlaneParams(threshold=0.015, min_inliers=400),
                           door=3.5, seed=14)
    assert not [c for c in found if c.kind == "doorway"]


def test_workplace_configuration():
    found, _, _ = _configs(scenes.workplace, PlaneParams(threshold=0.012, min_inliers=400),
                           table_height=0.75, seed=15)
    tables = [c for c in found if c.kind == "workplace"]
    assert len(tables) == 1
    assert tables[0].params["height"] == pytest.approx(0.75, abs=0.01)
    assert tables[0].params["area"] == pytest.approx(0.96, rel=0.1)
    n, rho = plane_to_hesse(tables[0].entities["table"])
    assert abs(n[2]) == pytest.approx(1.0, abs=1e-4) and rho == pytest.approx(0.75, abs=0.01)
    # a shelf at 1.5 m is not a workplace
    found, _, _ = _configs(scenes.workplace, PlaneParams(threshold=0.012, min_inliers=400),
                           table_height=1.5, seed=15)
    assert not [c for c in found if c.kind == "workplace"]


def test_configurations_in_a_camera_frame():
    """The same corridor seen in an OpenCV camera frame (y down) with up = (0, -1, 0)."""
    pts, _ = scenes.corridor(seed=16)
    cam = np.stack([-pts[:, 1], -pts[:, 2] + 1.2, pts[:, 0]], axis=1)  # x right, y down, z fwd
    planes = detect_planes(cam, "ransac", PlaneParams(threshold=0.015, min_inliers=400))
    kinds = [c.kind for c in find_configurations(planes, up=(0.0, -1.0, 0.0))]
    assert kinds == ["corridor"]


# ---- places --------------------------------------------------------------------------------


PLACES = {
    "corridor": (lambda s: scenes.corridor(seed=s)[0] - [3, 0, 0], 0.015),
    "doorway": (lambda s: scenes.doorway(seed=s)[0] - [1.5, 0, 0], 0.015),
    "workplace": (lambda s: scenes.workplace(seed=s)[0] - [1.5, 0, 0], 0.012),
    "room": (lambda s: scenes.three_planes(n=20_000, seed=s)[0], 0.03),
}


def _planes(pts, thr):
    return detect_planes(pts, "ransac", PlaneParams(threshold=thr, min_inliers=400))


def test_features_do_not_change_when_the_robot_turns():
    pts = PLACES["doorway"][0](1)
    f0 = place_features(_planes(pts, 0.015))
    for angle in (0.5, 2.0, -2.9):
        f = place_features(_planes(scenes.rotate_z(pts, angle), 0.015))
        assert np.linalg.norm(f - f0) < 0.02
    # while a different arrangement changes them
    other = place_features(_planes(PLACES["corridor"][0](1), 0.015))
    assert np.linalg.norm(other - f0) > 1.0


def test_place_recognition_on_a_revisit_with_the_robot_turned(tmp_path):
    db = PlaceDatabase()
    for name, (make, thr) in PLACES.items():
        db.add(name, _planes(make(10), thr))
    db.save(tmp_path / "places.json")
    db = PlaceDatabase.load(tmp_path / "places.json")
    rng = np.random.default_rng(4)
    for name, (make, thr) in PLACES.items():
        for visit in range(2):
            angle = rng.uniform(-np.pi, np.pi)
            shift = np.append(rng.normal(0, 0.03, 2), 0.0)
            pts = scenes.rotate_z(make(30 + visit), angle, shift)  # new noise, new pose
            got, dist = db.recognise(_planes(pts, thr))
            assert got == name, (name, np.degrees(angle), dist, db.distances(_planes(pts, thr)))
    # a corridor of another width is a new place
    wide = scenes.corridor(width=3.2, seed=5)[0] - [3, 0, 0]
    assert db.recognise(_planes(wide, 0.015))[0] is None


def test_merge_folds_a_bridged_pair_without_comparing_arrays():
    """An observation that touches two separate map patches of one wall folds them into one
    (regression: list.remove compared numpy fields with == and raised)."""
    from cgamap.mapping.planemap import PlaneMap
    from cgamap.mapping.planes import ransac_planes

    def patch(x0, x1):
        xs = np.linspace(x0, x1, 40)
        zs = np.linspace(0.0, 2.0, 40)
        X, Z = np.meshgrid(xs, zs)
        return np.stack([X.ravel(), np.full(X.size, 3.0), Z.ravel()], axis=1)

    m = PlaneMap()
    m.integrate(ransac_planes(patch(0.0, 1.0))[:1])
    m.integrate(ransac_planes(patch(2.0, 3.0))[:1])
    assert len(m.planes) == 2  # a 1 m gap: two patches of the wall
    m.integrate(ransac_planes(patch(0.9, 2.1))[:1])
    assert len(m.planes) == 1
