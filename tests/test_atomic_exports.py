"""Map exports are atomic: a write that fails (here: the final rename) leaves the previous file
whole and no temp file behind; a successful one replaces it."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest
from cgamap.daemon.demo import write_report
from cgamap.daemon.export import export, read_ply_counts, render_3d_png
from cgamap.mapping.linemap import LineMap
from cgamap.mapping.planemap import PlaneMap
from cgamap.mapping.render import export_occupancy, render_png, write_image_atomic


def _reply(n: int) -> dict:
    """A map reply with ``n`` wall segments and one camera plane."""
    x = np.arange(n, dtype=float)
    segs = np.c_[x, np.zeros(n), x + 0.8, np.ones(n)]
    plane = {"corners": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]}
    return {"segments": segs.tolist(), "planes": [plane]}


def _lmap(n: int) -> LineMap:
    seg = np.asarray(_reply(n)["segments"])
    return LineMap(a=seg[:, :2].copy(), b=seg[:, 2:].copy())


@pytest.fixture
def failing_rename(monkeypatch):
    """Call it to make every later os.replace fail (a full disk, a yanked USB stick)."""
    def arm():
        def boom(src, dst):
            raise OSError(28, "No space left on device", str(dst))

        monkeypatch.setattr(os, "replace", boom)
    return arm


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("fmt, name", [("json", "map.json"), ("ply", "map.ply"),
                                       ("png", "map.png"), ("pgm", "map.pgm")])
def test_failed_export_keeps_the_previous_files(fmt, name, tmp_path, failing_rename):
    files = export(_reply(2), fmt, tmp_path / name)
    assert all(f.is_file() for f in files)
    before = _snapshot(tmp_path)
    failing_rename()
    with pytest.raises(OSError, match="No space"):
        export(_reply(5), fmt, tmp_path / name)
    assert _snapshot(tmp_path) == before      # same bytes, and no .tmp left behind


def test_export_replaces_the_previous_files(tmp_path):
    export(_reply(2), "ply", tmp_path / "m.ply")
    export(_reply(5), "ply", tmp_path / "m.ply")
    assert read_ply_counts(tmp_path / "m.ply") == (4 * 6, 6)
    export(_reply(2), "json", tmp_path / "m.json")
    export(_reply(5), "json", tmp_path / "m.json")
    assert len(json.loads((tmp_path / "m.json").read_text())["segments"]) == 5
    pgm, yml = export(_reply(5), "pgm", tmp_path / "m.pgm")
    assert cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED).dtype == np.uint8
    assert "image: m.pgm" in yml.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.json", "m.pgm", "m.ply", "m.yaml"]


def test_render_writes_are_atomic(tmp_path, failing_rename):
    render_png(_lmap(2), tmp_path / "a.png")
    export_occupancy(_lmap(2), tmp_path / "occ")
    render_3d_png(_reply(2), tmp_path / "3d.png", size=(120, 80))
    img = cv2.imread(str(tmp_path / "a.png"))
    assert img is not None and img.ndim == 3 and (img == 0).any()  # black segments drawn
    before = _snapshot(tmp_path)
    failing_rename()
    with pytest.raises(OSError):
        render_png(_lmap(6), tmp_path / "a.png")
    with pytest.raises(OSError):
        export_occupancy(_lmap(6), tmp_path / "occ")
    with pytest.raises(OSError):
        render_3d_png(_reply(6), tmp_path / "3d.png", size=(120, 80))
    assert _snapshot(tmp_path) == before


def test_image_encoding_follows_the_extension(tmp_path):
    img = np.arange(64, dtype=np.uint8).reshape(8, 8)
    for name in ("i.png", "i.pgm"):
        write_image_atomic(tmp_path / name, img)
        assert np.array_equal(cv2.imread(str(tmp_path / name), cv2.IMREAD_UNCHANGED), img)
    assert (tmp_path / "i.pgm").read_bytes().startswith(b"P5")


def test_plane_map_ply_and_demo_report_are_atomic(tmp_path, failing_rename):
    pm = PlaneMap()
    pm.add_virtual_walls(np.array([[[0.0, 0.0], [4.0, 0.0]]]), height=2.4)
    pm.save_ply(tmp_path / "p.ply")
    report = {"world": "loop", "duration_s": 1.0, "truth": {"ate_trans_m": 0.1}}
    write_report(tmp_path, report)
    assert json.loads((tmp_path / "report.json").read_text())["world"] == "loop"
    assert "ATE translation" in (tmp_path / "report.md").read_text()
    before = _snapshot(tmp_path)
    pm.add_virtual_walls(np.array([[[4.0, 0.0], [4.0, 3.0]]]), height=2.4)
    failing_rename()
    with pytest.raises(OSError):
        pm.save_ply(tmp_path / "p.ply")
    with pytest.raises(OSError):
        write_report(tmp_path, {**report, "world": "room"})
    assert _snapshot(tmp_path) == before
