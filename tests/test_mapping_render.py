"""Map pictures: PNG of map + trajectory, PGM + YAML occupancy in map_server convention."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import yaml
from cgamap.mapping.linemap import LineMap
from cgamap.mapping.render import MAX_SIDE_PX, export_occupancy, render_png


def _box() -> LineMap:
    a = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]])
    b = np.roll(a, -1, axis=0)
    m = LineMap()
    m.a, m.b = a, b
    m.n_pts = np.full(4, 10.0)
    m.centroid = 0.5 * (a + b)
    m.scatter = np.zeros((4, 2, 2))
    m.n_obs = np.ones(4, int)
    m.created = m.last_seen = np.zeros(4, int)
    return m


def test_png_has_walls_and_trajectory(tmp_path):
    traj = np.array([[1.0, 1.0, 0.0], [3.0, 1.5, 0.0], [3.0, 2.5, 1.0]])
    render_png(_box(), tmp_path / "m.png", traj, resolution=0.05, border=0.5)
    img = cv2.imread(str(tmp_path / "m.png"))
    assert img.shape[:2] == (int(np.ceil(4.0 / 0.05)) + 1, int(np.ceil(5.0 / 0.05)) + 1)
    black = np.all(img < 60, axis=2)
    blue = (img[..., 0] > 150) & (img[..., 2] < 80)
    assert black.sum() > 500 and blue.sum() > 20


def test_pgm_yaml_map_server_convention(tmp_path):
    pgm, yml = export_occupancy(_box(), tmp_path / "occ", resolution=0.1, border=1.0)
    meta = yaml.safe_load(yml.read_text())
    assert meta["image"] == "occ.pgm" and meta["resolution"] == pytest.approx(0.1)
    assert meta["origin"][:2] == pytest.approx([-1.0, -1.0]) and meta["negate"] == 0
    img = cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and set(np.unique(img)) <= {0, 205}
    # the world point (2, 0) (middle of the bottom wall) is an occupied pixel: row from the
    # top = height - 1 - (y - origin_y) / res
    h = img.shape[0]
    col = round((2.0 - meta["origin"][0]) / 0.1)
    row = h - 1 - round((0.0 - meta["origin"][1]) / 0.1)
    assert img[row, col] == 0
    assert img[row - 10, col] == 205  # one metre inside the room: not a wall


def test_huge_extent_is_drawn_coarser_not_overflowing(tmp_path, caplog):
    """QA: a trajectory point at 1e308 m overflowed the image size (int cast of inf/huge)."""
    traj = np.array([[0.0, 0.0, 0.0], [1e12, 5.0, 0.0]])
    with caplog.at_level("WARNING", logger="cgamap.mapping.render"):
        render_png(_box(), tmp_path / "m.png", traj, resolution=0.05)
    img = cv2.imread(str(tmp_path / "m.png"))
    assert img is not None and max(img.shape[:2]) <= MAX_SIDE_PX
    assert "drawn at" in caplog.text
    with pytest.raises(ValueError, match="float"):
        render_png(_box(), tmp_path / "n.png", np.array([[-1e308, 0, 0], [1e308, 0, 0.0]]))
    with pytest.raises(ValueError, match="non-finite"):
        render_png(_box(), tmp_path / "n.png", np.array([[np.inf, 0, 0.0]]))
    pgm, yml = export_occupancy(LineMap(a=np.array([[0.0, 0.0]]), b=np.array([[1e9, 0.0]])),
                                tmp_path / "occ")
    assert max(cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED).shape) <= MAX_SIDE_PX
