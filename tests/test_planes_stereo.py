"""Planes from stereo: the synthetic corridor through SGBM, and `cgamap planes --stereo`."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from cgamap.daemon.cli import main as cli_main
from cgamap.mapping.configurations import find_configurations
from cgamap.mapping.planes import PlaneParams, detect_planes, plane_error

stereo_render = pytest.importorskip("cgamap.drivers.sim.stereo_render")
stereo = pytest.importorskip("cgamap.drivers.stereo")

# stereo depth noise grows with the square of the range
STEREO = PlaneParams(threshold=0.02, range_noise=0.003, min_inliers=1000)
# the simulated corridor: walls y = -1 and y = +1, floor z = 0 (drivers/sim/world.py)
CORRIDOR = [((0.0, 1.0, 0.0), 1.0), ((0.0, -1.0, 0.0), 1.0), ((0.0, 0.0, 1.0), 0.0)]


@pytest.fixture(scope="module")
def corridor_frame():
    grabber = stereo_render.SyntheticGrabber(world="corridor", pose=(2.0, 0.0, 0.0), tilt=0.3)
    return grabber, grabber.grab()


def test_synthetic_stereo_corridor_walls_floor_and_configuration(corridor_frame):
    grabber, frame = corridor_frame
    pts = stereo.frame_points_global(frame, mount=grabber.mount, max_depth=6.0)
    planes = detect_planes(pts, "ransac", STEREO)
    assert len(planes) >= 3
    for n, rho in CORRIDOR:
        errs = [plane_error(p.normal, p.rho, n, rho) for p in planes]
        ang, drho = min(errs, key=lambda e: e[0] + 40 * e[1])
        assert ang < 2.0 and drho < 0.05, (n, rho, ang, drho)
    corridors = [c for c in find_configurations(planes) if c.kind == "corridor"]
    assert len(corridors) == 1
    assert corridors[0].params["width"] == pytest.approx(2.0, abs=0.1)
    assert abs(corridors[0].params["axis_direction"][0]) > 0.99


def test_cli_planes_from_a_stereo_pair(tmp_path, corridor_frame, capsys):
    from cgamap.drivers.stereo_calib import save_calibration

    grabber, _ = corridor_frame
    M = grabber.camera_motor_at(0.0)[0]
    left, right, _ = stereo_render.render_pair(grabber.scene, M, grabber.calib, grabber.size)
    cv2.imwrite(str(tmp_path / "l.png"), left)
    cv2.imwrite(str(tmp_path / "r.png"), right)
    save_calibration(grabber.calib, tmp_path / "calib.yaml")
    rc = cli_main(["planes", "--stereo", str(tmp_path / "l.png"), str(tmp_path / "r.png"),
                   "--calib", str(tmp_path / "calib.yaml"), "--json", "--max-depth", "6"])
    assert rc == 0
    planes = json.loads(capsys.readouterr().out)["planes"]
    assert len(planes) >= 3
    # in the left camera's optical frame (y down, tilted 0.3 rad): the floor's normal is
    # mostly along -y/+z and the two walls' normals along +-x
    normals = np.array([p["normal"] for p in planes[:3]])
    assert sum(abs(n[0]) > 0.95 for n in normals) == 2
    assert sum(abs(n[1]) > 0.9 for n in normals) == 1
    # a missing image is a usage error
    assert cli_main(["planes", "--stereo", str(tmp_path / "x.png"), str(tmp_path / "r.png"),
                     "--calib", str(tmp_path / "calib.yaml")]) == 2
    assert "no such file" in capsys.readouterr().err
