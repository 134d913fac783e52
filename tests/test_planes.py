"""Plane detection: cloud readers, RANSAC and the ball-accumulator Hough transform, the CLI."""

from __future__ import annotations

import json
import os
import struct

import numpy as np
import pytest
from cgamap.cga import hesse_to_hough3d, plane_to_hesse, up
from cgamap.daemon.cli import main as cli_main
from cgamap.mapping import plane_scenes as scenes
from cgamap.mapping.pcd import (
    CloudFormatError,
    finite_points,
    lzf_decompress,
    read_cloud,
    read_pcd,
    read_ply,
    write_pcd_ascii,
)
from cgamap.mapping.planes import (
    BallAccumulator,
    PlaneParams,
    detect_planes,
    normal_angle_deg,
    plane_error,
)
from hypothesis import given, settings
from hypothesis import strategies as st


def _within(err: tuple[float, float], deg: float, metres: float) -> bool:
    return err[0] < deg and err[1] < metres


# ---- readers -------------------------------------------------------------------------------


def lzf_literal_only(data: bytes) -> bytes:
    """A valid (uncompressed) LZF stream: literal runs of at most 32 bytes."""
    out = bytearray()
    for i in range(0, len(data), 32):
        chunk = data[i:i + 32]
        out.append(len(chunk) - 1)
        out += chunk
    return bytes(out)


def test_lzf_back_references_including_overlap():
    # literal "ab", then a reference of length 5 at distance 2 (overlapping: repeats "ab")
    stream = bytes([1]) + b"ab" + bytes([(3 << 5) | 0, 1])
    assert lzf_decompress(stream, 7) == b"abababa"
    # long reference (length field 7 + extension byte) at distance 3
    stream = bytes([2]) + b"xyz" + bytes([(7 << 5) | 0, 4, 2])  # length 7 + 4 + 2 = 13
    assert lzf_decompress(stream, 16) == b"xyz" * 5 + b"x"
    with pytest.raises(ValueError):
        lzf_decompress(bytes([(1 << 5), 9]), 3)  # reference before the start
    with pytest.raises(ValueError):
        lzf_decompress(bytes([1]) + b"ab", 5)  # output shorter than announced


def _pcd_header(kind: str, w: int, h: int) -> bytes:
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\n"
            f"COUNT 1 1 1 1\nWIDTH {w}\nHEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {w * h}\n"
            f"DATA {kind}\n").encode()


@pytest.fixture
def organised():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 5, 3)).astype(np.float32)
    pts[1, 2] = np.nan
    return pts


def test_pcd_binary_and_compressed_round_trip(tmp_path, organised):
    h, w = organised.shape[:2]
    flat = organised.reshape(-1, 3)
    rgb = np.arange(h * w, dtype=np.uint32)
    rec = np.zeros(h * w, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"], rec["rgb"] = flat[:, 0], flat[:, 1], flat[:, 2], rgb
    (tmp_path / "b.pcd").write_bytes(_pcd_header("binary", w, h) + rec.tobytes())
    columns = b"".join(np.ascontiguousarray(rec[k]).tobytes() for k in ("x", "y", "z", "rgb"))
    comp = lzf_literal_only(columns)
    (tmp_path / "c.pcd").write_bytes(_pcd_header("binary_compressed", w, h)
                                     + struct.pack("<II", len(comp), len(columns)) + comp)
    for name in ("b.pcd", "c.pcd"):
        got = read_pcd(tmp_path / name)
        assert got.shape == (h, w, 3)
        np.testing.assert_array_equal(np.isnan(got), np.isnan(organised))
        np.testing.assert_allclose(got[np.isfinite(got)], organised[np.isfinite(organised)])
    write_pcd_ascii(tmp_path / "a.pcd", organised)
    np.testing.assert_allclose(read_cloud(tmp_path / "a.pcd"), organised, rtol=1e-6)


@pytest.mark.parametrize("body, problem", [
    (b"VERSION 0.7\nFIELDS x y\nSIZE 4 4\nTYPE F F\nWIDTH 1\nHEIGHT 1\nDATA ascii\n1 2\n",
     "no 'z' field"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 3\nHEIGHT 1\nDATA binary\n",
     "body is"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\nDATA zip\n",
     "unknown PCD DATA"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nDATA ascii\n1 2\n",
     "ascii PCD has"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\n", "no DATA line"),
    (b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 1\nHEIGHT 1\n"
     b"DATA binary_compressed\n" + struct.pack("<II", 50, 12) + b"\x00", "truncated"),
])
def test_malformed_pcd_names_file_and_problem(tmp_path, body, problem):
    path = tmp_path / "bad.pcd"
    path.write_bytes(body)
    with pytest.raises(CloudFormatError, match=problem) as info:
        read_pcd(path)
    assert str(path) in str(info.value)


def test_ply_ascii_and_binary(tmp_path):
    pts = np.array([[0.0, 1.0, 2.0], [3.5, -1.0, 0.25], [1e-3, 2.0, -7.0]])
    head = ("ply\nformat {fmt} 1.0\ncomment test\nelement vertex 3\nproperty float x\n"
            "property float y\nproperty float z\nproperty uchar red\nend_header\n")
    text = head.format(fmt="ascii") + "".join(f"{a} {b} {c} 7\n" for a, b, c in pts)
    (tmp_path / "a.ply").write_text(text)
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    rec["x"], rec["y"], rec["z"] = pts.T
    (tmp_path / "b.ply").write_bytes(head.format(fmt="binary_little_endian").encode()
                                     + rec.tobytes())
    np.testing.assert_allclose(read_ply(tmp_path / "a.ply"), pts, rtol=1e-6)
    np.testing.assert_allclose(read_cloud(tmp_path / "b.ply"), pts, rtol=1e-6)
    (tmp_path / "c.ply").write_text(head.format(fmt="binary_big_endian"))
    with pytest.raises(CloudFormatError, match="c.ply: PLY format"):
        read_ply(tmp_path / "c.ply")
    (tmp_path / "d.xyz").write_text("1 2 3\n")
    with pytest.raises(CloudFormatError, match="unknown cloud suffix"):
        read_cloud(tmp_path / "d.xyz")


def test_office1_pcd_is_read(shared_data):
    cloud = read_pcd(shared_data("clouds/office1.pcd"))
    assert cloud.shape == (480, 640, 3)
    assert len(finite_points(cloud)) == 254_456  # as SOURCES.md counts them


# ---- detection on synthetic clouds ---------------------------------------------------------


def _match(planes, truth):
    """Worst (angle deg, |d rho| m) over the truth planes, each matched to its best plane."""
    worst = (0.0, 0.0)
    for n, rho in truth:
        errs = [plane_error(p.normal, p.rho, n, rho) for p in planes]
        best = min(errs, key=lambda e: e[0] + 100 * e[1])
        worst = (max(worst[0], best[0]), max(worst[1], best[1]))
    return worst


@pytest.fixture(scope="module")
def bench_scene():
    return scenes.three_planes(n=100_000, outliers=0.2, noise=0.01, seed=7)


@pytest.mark.parametrize("method", ["ransac", "hough"])
def test_three_planes_found_within_targets(bench_scene, method):
    pts, truth = bench_scene
    planes = detect_planes(pts, method, PlaneParams(threshold=0.03, min_inliers=2000))
    assert len(planes) == 3
    ang, drho = _match(planes, truth)
    assert ang < 0.1 and drho < 0.002, (ang, drho)
    # each plane holds about its 26,666 points (plus the outliers that fall within 3 cm)
    assert all(25_000 < p.inliers < 29_000 for p in planes)
    assert [p.inliers for p in planes] == sorted((p.inliers for p in planes), reverse=True)


def test_plane_record_is_consistent(bench_scene):
    pts, _ = bench_scene
    for p in detect_planes(pts, "ransac", PlaneParams(threshold=0.03, min_inliers=2000)):
        t, ph, r = p.hough
        assert (t, ph, r) == pytest.approx(tuple(map(float, hesse_to_hough3d(p.normal, p.rho))))
        assert 0 <= t <= np.pi and -np.pi < ph <= np.pi and r >= 0
        n, rho = plane_to_hesse(p.cga())
        np.testing.assert_allclose(n, p.normal, atol=1e-9)
        assert rho == pytest.approx(p.rho)
        # the drawn corners lie on the CGA plane: X ^ P = 0 for a point X on an OPNS plane
        on = (up(p.corners) ^ p.cga()).v
        assert np.abs(on).max() < 1e-9
        # the corner rectangle contains the extent polygon's area, and both are about 10 m2
        assert 7 < p.area <= np.linalg.norm(np.cross(p.corners[1] - p.corners[0],
                                                     p.corners[3] - p.corners[0])) + 1e-6
        np.testing.assert_allclose(p.extent @ p.normal, p.rho, atol=1e-6)
        assert np.abs(pts[p.inlier_index] @ p.normal - p.rho).max() < 0.03
        d = p.to_dict()
        assert set(d) >= {"normal", "rho", "inliers", "hough", "corners", "extent", "cga"}
        assert len(d["cga"]) == 32


@pytest.mark.parametrize("method", ["ransac", "hough"])
def test_coplanar_distant_patches_are_two_planes(method):
    rng = np.random.default_rng(3)
    a = scenes.sample_rect((0, 0, 1.0), (1, 0, 0), (0, 1, 0), 1.0, 1.0, 4000, rng)
    b = scenes.sample_rect((3, 0, 1.0), (1, 0, 0), (0, 1, 0), 1.0, 1.0, 3000, rng)
    pts = np.concatenate([a, b]) + rng.normal(0, 0.002, (7000, 3))
    planes = detect_planes(pts, method, PlaneParams(threshold=0.01, min_inliers=1000))
    assert [p.inliers for p in planes] == [4000, 3000]
    for p in planes:
        assert normal_angle_deg(p.normal, (0, 0, 1)) < 0.5 and abs(p.rho - 1.0) < 0.005
        assert p.area == pytest.approx(1.0, abs=0.05)
    # with a region cell wider than the gap the two patches are one plane again
    wide = detect_planes(pts, method, PlaneParams(threshold=0.01, min_inliers=1000,
                                                  region_cell=2.5))
    assert wide[0].inliers == 7000


def test_range_noise_widens_the_threshold_with_distance():
    rng = np.random.default_rng(5)
    near = scenes.sample_rect((1, -1, -1), (0, 1, 0), (0, 0, 1), 2, 2, 3000, rng)
    far = scenes.sample_rect((1, -1, -1), (0, 1, 0), (0, 0, 1), 2, 2, 3000, rng)
    far = far * [5.0, 1, 1]  # x = 5
    # depth noise grows with range: 2 cm at 5 m
    pts = np.concatenate([near + rng.normal(0, 0.002, near.shape) * [1, 0, 0],
                          far + rng.normal(0, 0.02, far.shape) * [1, 0, 0]])
    tight = detect_planes(pts, "ransac", PlaneParams(threshold=0.01, min_inliers=500))
    wide = detect_planes(pts, "ransac", PlaneParams(threshold=0.01, range_noise=0.003,
                                                    min_inliers=500))
    far_tight = [p for p in tight if abs(p.rho - 5) < 0.1]
    far_wide = [p for p in wide if abs(p.rho - 5) < 0.1]
    assert far_wide and far_wide[0].inliers > 2900
    assert not far_tight or far_tight[0].inliers < 0.6 * far_wide[0].inliers


def test_detection_repeats_with_a_seed_and_handles_tiny_input(bench_scene):
    pts = bench_scene[0][:20_000]
    prm = PlaneParams(threshold=0.03, min_inliers=500)
    a = detect_planes(pts, "hough", prm, seed=11)
    b = detect_planes(pts, "hough", prm, seed=11)
    assert [p.inliers for p in a] == [p.inliers for p in b]
    # one far outlier stretches the rho range of the accumulator a thousandfold: no matter
    far = np.vstack([pts, [[1e4, 0.0, 0.0]]])
    got = detect_planes(far, "hough", prm, seed=11)
    assert len(got) == len(a) == 3
    np.testing.assert_allclose([p.inliers for p in got], [p.inliers for p in a], rtol=0.03)
    assert detect_planes(np.zeros((0, 3))) == []
    assert detect_planes(np.full((10, 10, 3), np.nan)) == []
    with pytest.raises(ValueError, match="unknown plane method"):
        detect_planes(pts, "magic")


def test_ball_accumulator_cells_are_of_about_equal_area():
    acc = BallAccumulator(np.radians(3.0), 0.05, 1.0)
    edges = np.linspace(0, np.pi, acc.n_rings + 1)
    ring_area = 2 * np.pi * (np.cos(edges[:-1]) - np.cos(edges[1:]))
    cell_area = ring_area / acc.ring_cells
    middle = cell_area[3:-3]  # the polar caps are single small rings by construction
    assert middle.max() / middle.min() < 1.1
    assert acc.cells_per_shell == pytest.approx(4 * np.pi / np.radians(3.0) ** 2, rel=0.05)
    # every cell's centre maps back to the cell
    cells = np.arange(acc.cells_per_shell * 2)
    centres = np.array([acc.cell_centre(c) for c in cells])
    assert np.array_equal(acc.cell_of(centres[:, 0], centres[:, 1], centres[:, 2]), cells)


# ---- CLI -----------------------------------------------------------------------------------


def test_cli_json_on_npy_cloud(tmp_path, capsys):
    pts, truth = scenes.corridor(seed=9)
    np.save(tmp_path / "c.npy", pts)
    assert cli_main(["planes", "--cloud", str(tmp_path / "c.npy"), "--json",
                     "--threshold", "0.02", "--method", "hough"]) == 0
    out = json.loads(capsys.readouterr().out)
    planes = out["planes"]
    assert len(planes) == 3
    assert [p["inliers"] for p in planes] == sorted((p["inliers"] for p in planes), reverse=True)
    for n, rho in truth:
        assert any(_within(plane_error(p["normal"], p["rho"], n, rho), 0.5, 0.01)
                   for p in planes)


def test_cli_text_and_errors(tmp_path, capsys):
    pts, _ = scenes.corridor(seed=9)
    write_pcd_ascii(tmp_path / "c.pcd", pts)
    assert cli_main(["planes", "--cloud", str(tmp_path / "c.pcd")]) == 0
    assert capsys.readouterr().out.startswith("3 planes in")
    assert cli_main(["planes", "--cloud", str(tmp_path / "none.ply")]) == 2
    assert "no such file" in capsys.readouterr().err
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement face 1\nend_header\n")
    assert cli_main(["planes", "--cloud", str(tmp_path / "bad.ply")]) == 2
    err = capsys.readouterr().err
    assert "bad.ply" in err and "vertex" in err and "Traceback" not in err
    assert cli_main(["planes", "--stereo", "l.png", "r.png"]) == 2
    assert "--calib" in capsys.readouterr().err
    assert cli_main(["planes", "--cloud", str(tmp_path / "c.pcd"), "--threshold", "0"]) == 2


def test_cli_configurations_and_exports(tmp_path, capsys):
    pts, _ = scenes.doorway(seed=2)
    np.save(tmp_path / "d.npy", pts)
    args = ["planes", "--cloud", str(tmp_path / "d.npy"), "--configurations",
            "--ply", str(tmp_path / "p.ply"), "--hough-png", str(tmp_path / "h.png")]
    assert cli_main(args + ["--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [c["kind"] for c in out["configurations"]] == ["doorway"]
    assert out["configurations"][0]["params"]["width"] == pytest.approx(0.9, abs=0.05)
    assert read_ply(tmp_path / "p.ply").shape == (4 * len(out["planes"]), 3)
    assert (tmp_path / "h.png").stat().st_size > 1000
    assert cli_main(args) == 0
    assert "doorway: planes" in capsys.readouterr().out
    assert cli_main(args[:3] + ["--ply", str(tmp_path / "no" / "p.ply")]) == 2
    assert "export" in capsys.readouterr().err


@settings(max_examples=30, deadline=None, derandomize=True)
@given(theta=st.floats(0.0, np.pi), phi=st.floats(-np.pi, np.pi), rho=st.floats(0.0, 4.0),
       method=st.sampled_from(["ransac", "hough"]))
def test_any_orientation_is_recovered(theta, phi, rho, method):
    """Poles of the ball (theta near 0 or pi), the phi seam at +-pi and rho = 0 included."""
    n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    rng = np.random.default_rng(0)
    plane_pts = scenes.sample_rect(n * rho - 1.5 * u - 1.5 * v, u, v, 3.0, 3.0, 4000, rng)
    pts = np.concatenate([plane_pts + rng.normal(0, 0.003, plane_pts.shape),
                          rng.uniform(-3, 3, (1000, 3)) + n * rho])
    planes = detect_planes(pts, method, PlaneParams(threshold=0.01, min_inliers=1500))
    assert len(planes) == 1
    p = planes[0]
    assert normal_angle_deg(p.normal, n) < 0.3
    # same plane, in the canonical form (rho >= 0): n and rho flip together near rho = 0
    sign = np.sign(p.normal @ n)
    assert abs(sign * p.rho - rho) < 0.003
    t, ph, r = p.hough
    assert 0 <= t <= np.pi and -np.pi < ph <= np.pi and r >= 0


FUZZ_EXAMPLES = int(os.environ.get("CGAMAP_FUZZ_EXAMPLES", "5000"))


def _valid_files(tmp_dir):
    pts = np.arange(36, dtype=np.float32).reshape(12, 3) / 7
    rec = np.zeros(12, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])
    rec["x"], rec["y"], rec["z"] = pts.T
    columns = b"".join(np.ascontiguousarray(rec[k]).tobytes() for k in ("x", "y", "z", "rgb"))
    comp = lzf_literal_only(columns)
    return {
        "b.pcd": _pcd_header("binary", 4, 3) + rec.tobytes(),
        "c.pcd": _pcd_header("binary_compressed", 4, 3)
        + struct.pack("<II", len(comp), len(columns)) + comp,
        "a.pcd": _pcd_header("ascii", 4, 3).replace(b"TYPE F F F U", b"TYPE F F F F")
        + b"\n".join(b"%g %g %g 0" % tuple(p) for p in pts) + b"\n",
        "a.ply": b"ply\nformat ascii 1.0\nelement vertex 12\nproperty float x\n"
                 b"property float y\nproperty float z\nend_header\n"
                 + b"\n".join(b"%g %g %g" % tuple(p) for p in pts) + b"\n",
    }


@pytest.mark.parametrize("name", ["b.pcd", "c.pcd", "a.pcd", "a.ply"])
def test_fuzzed_cloud_files_fail_only_with_a_clear_error(tmp_path, name):
    """Random byte flips, truncations and insertions: the reader returns a cloud or raises
    CloudFormatError naming the file, never another exception."""
    _fuzz_reader(tmp_path, name, 60)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["b.pcd", "c.pcd", "a.pcd", "a.ply"])
def test_fuzz_cloud_readers_long(tmp_path, name):
    _fuzz_reader(tmp_path, name, FUZZ_EXAMPLES // 4)


def _fuzz_reader(tmp_path, name: str, examples: int) -> None:
    good = _valid_files(tmp_path)[name]
    (tmp_path / name).write_bytes(good)
    assert read_cloud(tmp_path / name).reshape(-1, 3).shape == (12, 3)

    @settings(max_examples=examples, deadline=None, derandomize=True)
    @given(data=st.data())
    def mutate(data):
        raw = bytearray(good)
        for _ in range(data.draw(st.integers(1, 4))):
            kind = data.draw(st.sampled_from(["flip", "cut", "insert"]))
            pos = data.draw(st.integers(0, len(raw) - 1))
            if kind == "flip":
                raw[pos] = data.draw(st.integers(0, 255))
            elif kind == "cut":
                del raw[pos:pos + data.draw(st.integers(1, 40))]
            else:
                raw[pos:pos] = data.draw(st.binary(min_size=1, max_size=8))
            if not raw:
                raw = bytearray(b"x")
        path = tmp_path / name
        path.write_bytes(bytes(raw))
        try:
            cloud = read_cloud(path)
        except CloudFormatError as exc:
            assert str(path) in str(exc)
            return
        assert cloud.shape[-1] == 3

    mutate()


def test_broken_npy_files_are_cloud_format_errors(tmp_path):
    """QA: np.load's EOFError (empty file) escaped the reader."""
    (tmp_path / "empty.npy").write_bytes(b"")
    full = tmp_path / "full.npy"
    np.save(full, np.zeros((100, 3)))
    (tmp_path / "cut.npy").write_bytes(full.read_bytes()[:200])
    (tmp_path / "junk.npy").write_bytes(bytes(range(256)))
    np.savez(tmp_path / "arch.npz", a=np.zeros((3, 3)))
    (tmp_path / "arch.npz").rename(tmp_path / "arch.npy")
    np.save(tmp_path / "text.npy", np.array([["a", "b", "c"]]))
    for name in ("empty", "cut", "junk", "arch", "text"):
        with pytest.raises(CloudFormatError, match=f"{name}.npy"):
            read_cloud(tmp_path / f"{name}.npy")
