"""Plane detection on real data: PCL's office1.pcd (RGB-D) and Middlebury venus (disparity)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from cgamap.mapping.pcd import finite_points, read_pcd
from cgamap.mapping.planes import (
    PlaneParams,
    detect_planes,
    fit_plane_lsq,
    largest_region,
    normal_angle_deg,
    plane_error,
)
from conftest import require_data

# office1 is a Kinect cloud: depth comes in disparity steps of about 0.003 z^2 (7.5 cm at
# 5 m), so the inlier band widens with range as it does in the detector's own parameters.
OFFICE = PlaneParams(threshold=0.015, range_noise=0.003, min_inliers=3000, max_planes=5)


def reference_planes(pts: np.ndarray, prm: PlaneParams, count: int, hypotheses: int = 3000,
                     seed: int = 123) -> list[tuple[np.ndarray, float, int]]:
    """A slow, careful sequential fit, independent of the detector's shortcuts: hypotheses
    from *global* random triples scored on a large sample, then least squares iterated on all
    unclaimed points until the inlier set stops changing, with the largest connected region.
    """
    rng = np.random.default_rng(seed)
    thr = prm.threshold + prm.range_noise * np.einsum("ij,ij->i", pts, pts)
    active = np.ones(len(pts), dtype=bool)
    out = []
    for _ in range(count):
        rem = np.flatnonzero(active)
        sample = rem[rng.choice(len(rem), size=min(30_000, len(rem)), replace=False)]
        tri = pts[rem[rng.integers(0, len(rem), size=(hypotheses, 3))]]
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-300
        rho = np.einsum("ij,ij->i", nrm, tri[:, 0])
        score = np.zeros(hypotheses, dtype=np.int64)
        for k in range(0, hypotheses, 500):
            d = np.abs(pts[sample] @ nrm[k:k + 500].T - rho[k:k + 500])
            score[k:k + 500] = (d < thr[sample, None]).sum(axis=0)
        best = int(np.argmax(score))
        n, r = nrm[best], rho[best]
        members = np.zeros(0, dtype=np.intp)
        for _ in range(50):
            new = np.flatnonzero((np.abs(pts @ n - r) < thr) & active)
            new = new[largest_region(pts[new], n, prm.region_cell)]
            if np.array_equal(new, members):
                break
            members = new
            n, r, _ = fit_plane_lsq(pts[members])
        active[members] = False
        out.append((n, r, len(members)))
    return out


@pytest.fixture(scope="module")
def office():
    return finite_points(read_pcd(require_data("clouds/office1.pcd")))


@pytest.fixture(scope="module")
def office_reference(office):
    return reference_planes(office, OFFICE, count=7)


@pytest.mark.parametrize("method,count", [("ransac", 5), ("hough", 4)])
def test_office1_largest_planes_match_careful_fit(office, office_reference, method, count):
    planes = detect_planes(office, method, OFFICE)
    assert len(planes) >= count
    for p in planes[:count]:
        errs = [plane_error(p.normal, p.rho, n, r) for n, r, _ in office_reference]
        ang, drho = min(errs, key=lambda e: e[0] / 1.0 + e[1] / 0.02)
        assert ang < 1.0 and drho < 0.02, (p.normal, p.rho, ang, drho)
    # the reference's two largest planes (back wall, side wall) are the detector's two largest
    for (n, r, size), p in zip(office_reference[:2], planes[:2], strict=True):
        ang, drho = plane_error(p.normal, p.rho, n, r)
        assert ang < 1.0 and drho < 0.02
        assert p.inliers == pytest.approx(size, rel=0.05)


def test_venus_disparity_is_piecewise_planar(shared_data):
    """Middlebury venus ground truth: planes in space stay planes in (x, y, d)."""
    path = shared_data("stereo/middlebury/venus/disp2.pgm")
    disp = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(float) / 8.0
    h, w = disp.shape
    y, x = np.mgrid[0:h, 0:w]
    cloud = np.stack([x, y, disp], axis=-1).astype(float)
    cloud[disp == 0] = np.nan
    valid = int((disp > 0).sum())
    prm = PlaneParams(threshold=0.3, min_inliers=2000, region_cell=3.0, neighbourhood=15.0)
    found = {}
    for method in ("ransac", "hough"):
        planes = detect_planes(cloud, method, prm)
        top = planes[:4]
        # four slanted planes explain >90% of the pixels, to the 1/8 px quantisation
        assert sum(p.inliers for p in top) > 0.9 * valid
        assert all(p.rms < 0.06 for p in top)
        found[method] = top
    for a, b in zip(found["ransac"], found["hough"], strict=True):
        ang, drho = plane_error(a.normal, a.rho, b.normal, b.rho)
        assert ang < 0.5 and drho < 0.2


def test_venus_sgbm_disparity_recovers_the_ground_truth_planes(shared_data):
    """The same planes from the real stereo pair through StereoSGBM."""
    base = shared_data("stereo/middlebury/venus/im2.png").parent
    left = cv2.imread(str(base / "im2.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(base / "im6.png"), cv2.IMREAD_GRAYSCALE)
    truth = cv2.imread(str(base / "disp2.pgm"), cv2.IMREAD_UNCHANGED).astype(float) / 8.0
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=32, blockSize=5,
                                 P1=8 * 25, P2=32 * 25, uniquenessRatio=10,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disp = sgbm.compute(left, right).astype(float) / 16.0
    h, w = disp.shape
    y, x = np.mgrid[0:h, 0:w]
    cloud = np.stack([x, y, disp], axis=-1)
    cloud[(disp <= 0) | (x < 40)] = np.nan  # SGBM leaves the left border unmatched
    prm = PlaneParams(threshold=0.5, min_inliers=3000, region_cell=3.0, neighbourhood=15.0,
                      max_planes=4)
    planes = detect_planes(cloud, "ransac", prm)
    gt_cloud = np.stack([x, y, truth], axis=-1).astype(float)
    gt_cloud[truth == 0] = np.nan
    gt = detect_planes(gt_cloud, "ransac", PlaneParams(threshold=0.3, min_inliers=2000,
                                                       region_cell=3.0, neighbourhood=15.0))
    # each of the three largest SGBM planes predicts the true disparity on its pixels
    flat = gt_cloud.reshape(-1, 3)
    finite = np.flatnonzero(np.all(np.isfinite(cloud.reshape(-1, 3)), axis=1))
    for p in planes[:3]:
        pix = finite[p.inlier_index]
        pix = pix[np.isfinite(flat[pix, 2])]
        pred = (p.rho - flat[pix, :2] @ p.normal[:2]) / p.normal[2]
        assert np.median(np.abs(pred - flat[pix, 2])) < 0.25
        assert any(normal_angle_deg(p.normal, g.normal) < 1.0 for g in gt[:5])


def _slices(planes: list[tuple[np.ndarray, float]]) -> list[tuple[int, int]]:
    """Pairs of parallel planes (< 1 deg) a depth step apart (< 0.12 m): one surface cut into
    the depth camera's quantisation levels."""
    return [(i, j) for i in range(len(planes)) for j in range(i + 1, len(planes))
            if (lambda e: e[0] < 1.0 and e[1] < 0.12)(plane_error(*planes[i], *planes[j]))]


def test_office1_reference_is_not_depth_slices(office, office_reference):
    """The careful reference must not be fooled by the Kinect's depth steps (7 cm at 5 m): its
    largest plane (the door wall) spans several of them, and no two of its planes are
    parallel slices of one surface."""
    assert not _slices([(n, r) for n, r, _ in office_reference])
    n, r, _ = office_reference[0]
    band = OFFICE.threshold + OFFICE.range_noise * np.einsum("ij,ij->i", office, office)
    levels, counts = np.unique(office[np.abs(office @ n - r) < band, 2], return_counts=True)
    # several well-populated steps, not one exact z level
    assert (counts > 0.1 * counts.sum()).sum() >= 2 and abs(n[2]) < 0.99999


@pytest.mark.parametrize("method", ["ransac", "hough"])
def test_cli_defaults_give_the_door_wall_as_one_plane(office_reference, method, capsys):
    """QA: `cgamap planes --cloud office1.pcd` (fixed 2 cm band) returned the door wall as
    four planes n = (0, 0, 1), rms 0, at the depth steps 4.906 ... 5.125 m.  The organised
    cloud now gets the range-dependent band by default."""
    import json

    from cgamap.daemon.cli import main

    path = require_data("clouds/office1.pcd")
    assert main(["planes", "--cloud", str(path), "--method", method, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["range_noise"] == pytest.approx(0.003)
    planes = [(np.array(p["normal"]), p["rho"]) for p in out["planes"]]
    assert all(p["rms"] > 0.001 for p in out["planes"])
    assert not _slices(planes)
    wall_n, wall_r, _ = office_reference[0]
    close = [p for p in planes if (lambda e: e[0] < 1.0 and e[1] < 0.02)(
        plane_error(*p, wall_n, wall_r))]
    assert len(close) == 1
