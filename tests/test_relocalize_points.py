"""Point-based verification of relocalisation hypotheses: the nearest-segment field, the
batched point-to-segment ICP, the free-space crossing count, the ranking, and the
all-rotation sweep for cluttered scans -- on hand-made maps with known answers."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cgamap.mapping.linemap import LineMap
from cgamap.mapping.pose_verify import (
    best_distinct,
    crossed_fractions,
    distinct_cells,
    icp_poses,
    inlier_scores,
)
from cgamap.mapping.posegraph import wrap
from cgamap.mapping.relocalize import (
    DistanceField,
    Hypothesis,
    RelocParams,
    _ranked,
    relocalize,
)
from cgamap.mapping.segments import Segments, segments_from_scan
from cgamap.mapping.sweep import (
    coarse_to_fine,
    correlative_sweep,
    fallback_sweep,
    reach_bound,
    tie_noise,
    top_cells,
    window_counts,
)
from hypothesis import given, settings
from hypothesis import strategies as st
from synth2d import ROOM, scan, scanned_map, world


def _segment_map(walls) -> LineMap:
    """A map holding exactly the given walls (x1, y1, x2, y2)."""
    w = np.asarray(walls, float)
    return LineMap(a=w[:, :2].copy(), b=w[:, 2:].copy(), n_pts=np.full(len(w), 10.0),
                   n_obs=np.full(len(w), 3))


def _pose_err(a, b) -> tuple[float, float]:
    return float(np.hypot(*(np.asarray(a)[:2] - np.asarray(b)[:2]))), float(
        np.degrees(abs(wrap(a[2] - b[2]))))


def test_nearest_names_the_segment_and_its_exact_distances():
    m = _segment_map([(0, 0, 4, 0), (5, 1, 5, 4)])
    f = DistanceField(m, 0.05)
    x = np.array([1.0, 2.0, 4.8, 4.5, 5.3])
    y = np.array([0.3, -0.2, 2.0, -0.5, 4.5])
    sid, e, dseg, ok = f.nearest(x, y)
    assert ok.all()
    assert sid.tolist() == [0, 0, 1, 0, 1]
    # signed distance to the line: exact, not quantised to the 5 cm grid
    assert e[0] == pytest.approx(0.3, abs=1e-9) and e[1] == pytest.approx(-0.2, abs=1e-9)
    assert abs(e[2]) == pytest.approx(0.2, abs=1e-9)
    # beyond a segment's end the distance is to the end point, not to the line
    assert dseg[3] == pytest.approx(np.hypot(0.5, 0.5), abs=1e-9)
    assert e[3] == pytest.approx(-0.5, abs=1e-9)
    assert dseg[4] == pytest.approx(np.hypot(0.3, 0.5), abs=1e-9)
    # off the grid: flagged, and counted as far
    _, _, d_off, ok_off = f.nearest(np.array([100.0]), np.array([0.0]))
    assert not ok_off[0] and d_off[0] >= f.far


def test_icp_pulls_many_starts_onto_the_true_pose():
    w = world(ROOM)
    m = _segment_map(ROOM)
    f = DistanceField(m, 0.05)
    p = np.array([0.7, 0.4, 0.3])
    pts = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi, sigma=0.005, seed=3)).points
    rng = np.random.default_rng(0)
    starts = p + np.column_stack([rng.uniform(-0.25, 0.25, (8, 2)),
                                  rng.uniform(-0.08, 0.08, 8)])
    out = icp_poses(f, pts, starts, RelocParams().icp_gates + RelocParams().final_gates)
    assert out.shape == starts.shape
    for q in out:
        et, er = _pose_err(q, p)
        assert et < 0.01 and er < 0.2


def _icp_numpy(field, pts, poses, gates):
    """:func:`icp_poses`'s step in numpy over (poses x points) arrays: the formulation the
    compiled kernel must agree with."""
    x = np.array(poses, dtype=float, copy=True)
    px, py = pts[None, :, 0], pts[None, :, 1]
    for gate in gates:
        c, s = np.cos(x[:, 2])[:, None], np.sin(x[:, 2])[:, None]
        rx, ry = c * px - s * py, s * px + c * py
        _, e, dseg, _, ux, uy, t, L = field.nearest(rx + x[:, :1], ry + x[:, 1:2], full=True)
        over = np.where(t < 0.0, t, np.where(t > L, t - L, 0.0))
        beyond = over != 0.0
        inv = 1.0 / np.maximum(dseg, 1e-9)
        nx = np.where(beyond, (over * ux - e * uy) * inv, -uy)
        ny = np.where(beyond, (over * uy + e * ux) * inv, ux)
        e = np.where(beyond, dseg, e)
        w = (dseg < gate) / (1.0 + (e / max(gate / 3.0, 0.02)) ** 2)
        J = np.stack([nx, ny, ny * rx - nx * ry], -1)
        A = np.einsum("hn,hni,hnj->hij", w, J, J) + np.eye(3) * 0.5
        x -= np.linalg.solve(A, np.einsum("hn,hni,hn->hi", w, J, e)[..., None])[..., 0]
    x[:, 2] = wrap(x[:, 2])
    return x


def test_compiled_icp_is_the_numpy_gauss_newton():
    # many starts all over a map of rooms (some off the grid, some beyond segment ends):
    # the compiled passes land where the (poses x points) numpy ones do
    m, _ = _rooms_map()
    field = DistanceField(m, 0.05, border=1.0)
    rng = np.random.default_rng(8)
    pts = rng.uniform(-6, 6, (48, 2))
    lo, hi = field.lo - 2, field.lo + field.size * field.res + 2
    poses = np.column_stack([rng.uniform(lo, hi, (200, 2)), rng.uniform(-np.pi, np.pi, 200)])
    P = RelocParams()
    for gates in (P.icp_gates, P.final_gates, (3.0, 1.5)):     # 3 m: beyond the border
        got, want = icp_poses(field, pts, poses, gates), _icp_numpy(field, pts, poses, gates)
        assert np.allclose(got, want, rtol=0, atol=1e-9)
        assert np.abs(got - poses).max() > 0.05          # the passes moved the poses


def test_icp_fixes_the_position_along_a_corridor_by_its_end():
    # a corridor closed at one end: the side walls fix y and theta only; the end wall's
    # points and the side walls' ends fix x
    walls = [(-8, -1, 2, -1), (-8, 1, 2, 1), (2, -1, 2, 1)]
    w, m = world(walls), _segment_map(walls)
    p = np.array([-1.0, 0.1, 0.05])
    pts = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi, max_range=6.0)).points
    P = RelocParams()
    out = icp_poses(DistanceField(m, 0.05), pts, (p + [0.3, 0.0, 0.0])[None],
                    P.icp_gates + P.final_gates)
    assert _pose_err(out[0], p)[0] < 0.02


def test_crossings_count_beams_through_walls_not_grazing_ones():
    walls = [(-5, -3, 5, -3), (5, -3, 5, 3), (5, 3, -5, 3), (-5, 3, -5, -3), (0, -1, 0, 1)]
    w, m = world(walls), _segment_map(walls)
    f = DistanceField(m, 0.05)
    P = RelocParams()
    p = np.array([-2.5, 0.0, 0.0])   # facing the free-standing wall at x = 0
    pts = segments_from_scan(scan(w, p, n=180)).points
    # at the true pose no beam passes through a wall, though beams near the room's
    # corners graze the side walls
    assert crossed_fractions(f, pts, p[None], P)[0] == 0.0
    # moved so the beams that ended on the free-standing wall now end behind it and the
    # others cross nothing: only the shifted beams that pass x = 0 count
    moved = p + [2.0, 0.0, 0.0]
    c = crossed_fractions(f, pts, np.stack([p, moved]), P)
    assert c[0] == 0.0 and 0.1 < c[1] < 0.9


def _crossings_numpy(field, pts, poses, P):
    """:func:`crossed_fractions` over (poses x beams x samples) arrays in numpy: the formulation
    the compiled kernel must agree with, beam for beam."""
    pts = pts[np.linspace(0, len(pts) - 1, P.cross_beams).astype(int)]
    r = np.linalg.norm(pts, axis=-1)
    f = np.arange(P.cross_skip, min(float(r.max()), P.cross_range), P.crossing_step)
    u = pts / r[:, None]
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    ugx = c[:, None] * u[None, :, 0] - s[:, None] * u[None, :, 1]
    ugy = s[:, None] * u[None, :, 0] + c[:, None] * u[None, :, 1]
    ox, oy = poses[:, 0, None, None], poses[:, 1, None, None]
    sx, sy = ox + ugx[..., None] * f, oy + ugy[..., None] * f
    near = field.lookup_xy(sx, sy) < 0.6 * P.crossing_step + 0.5 * field.res
    near &= f[None, None, :] < (r[None, :, None] - P.cross_margin)
    hit = np.zeros(near.shape[:2], bool)
    h, b, k = np.nonzero(near)
    sid = field.nearest(sx[h, b, k], sy[h, b, k])[0]
    ax, ay, wx, wy = field.a[sid, 0], field.a[sid, 1], field.u[sid, 0], field.u[sid, 1]
    o_x, o_y = ox[h, 0, 0], oy[h, 0, 0]
    ex, ey = o_x + ugx[h, b] * r[b], o_y + ugy[h, b] * r[b]
    so, se = -wy * (o_x - ax) + wx * (o_y - ay), -wy * (ex - ax) + wx * (ey - ay)
    lam = so / np.where(so != se, so - se, 1.0)
    along = wx * (o_x - ax + lam * (ex - o_x)) + wy * (o_y - ay + lam * (ey - o_y))
    m = P.cross_margin
    crossed = (np.sign(so) != np.sign(se)) & (np.abs(so) > m) & (np.abs(se) > m) & (
        along > 0.0) & (along < field.seg_len[sid])
    hit[h[crossed], b[crossed]] = True
    return hit.mean(-1)


def test_compiled_crossings_are_the_numpy_count():
    # poses all over a map of rooms, some off the grid: the same fraction of crossed beams
    m, walls = _rooms_map()
    field = DistanceField(m, 0.05)
    seg = segments_from_scan(scan(world(walls), (20.7, 11.6, 0.4), n=360, fov=2 * np.pi,
                                  sigma=0.005, seed=2))
    rng = np.random.default_rng(9)
    lo, hi = field.lo - 2, field.lo + field.size * field.res + 2
    poses = np.column_stack([rng.uniform(lo, hi, (300, 2)), rng.uniform(-np.pi, np.pi, 300)])
    P = RelocParams()
    got, want = crossed_fractions(field, seg.points, poses, P), _crossings_numpy(field, seg.points,
                                                                                 poses, P)
    assert np.array_equal(got, want) and 0.05 < np.mean(got > 0) < 0.95


def test_ranking_prefers_fit_less_crossings_and_merges_duplicates():
    P = RelocParams()
    a = Hypothesis(np.array([0.0, 0.0, 0.0]), 0.95, 0.90, 0.0)
    b = Hypothesis(np.array([5.0, 0.0, 0.0]), 0.95, 0.92, 0.5)   # fits, but through walls
    c = Hypothesis(np.array([0.03, 0.0, 0.005]), 0.95, 0.89, 0.0)  # a again
    r = _ranked([b, c, a], P)
    assert r.found and r.pose is a.pose and len(r.hypotheses) == 2
    # the loop closer ranks by the inlier fraction alone (fit_weight 0)
    r0 = _ranked([a, Hypothesis(np.array([5.0, 0.0, 0.0]), 0.97, 0.5, 0.9)],
                 replace(P, fit_weight=0.0))
    assert r0.pose[0] == 5.0
    assert not _ranked([Hypothesis(np.zeros(3), 0.3, 0.3, 0.0)], P).found


def test_two_identical_rooms_are_told_apart_by_free_space():
    # two equal rooms side by side; the right one has a free-standing wall the scan (taken
    # in the left one) would pass through: the points fit both rooms, free space only one
    room = [(0, 0, 6, 0), (6, 0, 6, 4), (6, 4, 0, 4), (0, 4, 0, 0)]
    right = [(x1 + 10, y1, x2 + 10, y2) for x1, y1, x2, y2 in room]
    w = world(room)
    m = _segment_map(room + right + [(13, 1.5, 13, 2.5)])
    p = np.array([1.5, 2.0, 0.0])
    r = relocalize(m, segments_from_scan(scan(w, p, n=360, fov=2 * np.pi)))
    assert r.found
    et, er = _pose_err(r.pose, p)
    assert et < 0.05 and er < 0.5
    twin = [h for h in r.hypotheses if _pose_err(h.pose, p + [10, 0, 0])[0] < 0.1]
    assert twin and twin[0].crossing > r.hypotheses[0].crossing


def test_single_line_scan_is_placed_by_its_points():
    # only one segment survives (the others are dropped); the sweep places the points
    w = world(ROOM)
    m = scanned_map(w, [(0.0, 0.0, 0.0), (2.0, 1.0, 0.0)])
    p = np.array([1.0, 0.5, 0.4])
    seg = segments_from_scan(scan(w, p, n=360, fov=2 * np.pi))
    one = seg.subset(np.argsort(-seg.length)[:1])
    r = relocalize(m, one)
    assert r.found
    # the room has a point symmetry only if it is centred: it is not, so the best wins
    et, er = _pose_err(r.pose, p)
    assert et < 0.05 and er < 0.5
    # without the sweep a single line is "not found" (the loop closer's setting)
    assert not relocalize(m, one, None, replace(RelocParams(), sweep_cells=0)).found


def _cluttered_scan(p) -> Segments:
    """A scan of ROOM from ``p`` whose only segment is clutter at an odd angle (a cabinet,
    not in the map), so the line pairing proposes wrong rotations; the room's walls are
    only points."""
    full = segments_from_scan(scan(world(ROOM), p, n=360, fov=2 * np.pi, sigma=0.005, seed=1))
    t = np.linspace(0, 1, 12)[:, None]
    a, b = np.array([0.6, 0.2]), np.array([1.0, 0.75])       # laser frame, ~0.7 m
    clutter = a + t * (b - a)
    pts = np.concatenate([full.points[::2], clutter])
    return Segments(a[None], b[None], np.array([12]), np.array([0.0]), (0.5 * (a + b))[None],
                    np.zeros((1, 2, 2)), np.zeros((1, 2, 2)), pts)


def test_cluttered_scan_found_by_the_all_rotation_sweep():
    m = _segment_map(ROOM)
    p = np.array([-0.5, 0.8, 1.1])
    seg = _cluttered_scan(p)
    P = RelocParams()
    r = relocalize(m, seg, None, P)
    assert r.found
    et, er = _pose_err(r.pose, p)
    assert et < 0.05 and er < 0.5
    # the fallback is what found it: without it the line pairing's rotations miss
    r_off = relocalize(m, seg, None, replace(P, fallback_fit=0.0))
    assert not r_off.found or _pose_err(r_off.pose, p)[1] > 2.0


def test_fallback_reads_the_free_space_band_not_the_map_area():
    # the same room in three maps: alone; with a 1 m wall piece 40 m away (the map's grid
    # 15x larger, nearly all of it empty); alone with a field border of 12 m instead of 2 m
    # (9x the grid).  The all-rotation sweep reads only positions near walls, so its reads
    # do not follow the map's area -- and it still finds the cluttered scan's pose
    p = np.array([-0.5, 0.8, 1.1])
    seg = _cluttered_scan(p)
    P = RelocParams()
    room = _segment_map(ROOM)
    far = _segment_map(ROOM + [(36.0, 30.0, 37.0, 30.0)])
    fields = {"room": DistanceField(room, 0.05), "far": DistanceField(far, 0.05),
              "border": DistanceField(room, 0.05, border=12.0)}
    maps = {"room": room, "far": far, "border": room}
    reach = reach_bound(seg.points, P, 0.05)
    step = int(round(P.fallback_grid / 0.05))
    grid, pos = {}, {}
    for k, f in fields.items():
        counts: dict = {}
        T, th = fallback_sweep(f, seg.points, P, reach, counts)
        assert counts["rotations"] == round(360 / P.fallback_rot_deg)
        assert len(T) == counts["rotations"] * P.fallback_cells
        grid[k], pos[k] = int(np.prod(f.grid_shape(step))), counts["positions"]
        r = relocalize(maps[k], seg, f, P)
        assert r.found and _pose_err(r.pose, p)[0] < 0.05 and _pose_err(r.pose, p)[1] < 0.5
    assert grid["far"] > 12 * grid["room"] and grid["border"] > 4 * grid["room"]
    # reads are bounded by the band: the walls' boxes grown by the reach, whatever the grid
    g = P.fallback_grid
    r_cells = (reach + 0.71 * g) / g
    room_box = (7.0 / g + 2 * r_cells + 2) * (5.0 / g + 2 * r_cells + 2)   # ROOM is 7 x 5 m
    piece_box = (1.0 / g + 2 * r_cells + 2) * (2 * r_cells + 2)           # the 1 m piece
    assert pos["border"] <= room_box < grid["border"] / 2
    assert pos["room"] < pos["far"] <= room_box + piece_box < grid["far"] / 5

def test_reach_bounds_the_nearest_wall_of_an_acceptable_pose():
    # 10 points at ranges 1..10: with min_score 0.5 at least 5 are inliers, the nearest of
    # them at most at range 6 (the 6th shortest), so a wall is within 6 + inlier_dist
    P = replace(RelocParams(), min_score=0.5, inlier_dist=0.1)
    ang = np.linspace(0, 2, 10)
    pts = np.column_stack([np.cos(ang), np.sin(ang)]) * np.arange(1, 11)[:, None]
    assert reach_bound(pts, P, 0.05) == pytest.approx(6.0 + 0.1 + 0.1)
    assert reach_bound(pts, replace(P, min_score=1.0), 0.05) == pytest.approx(1.2)
    assert reach_bound(pts, replace(P, min_score=0.0), 0.05) == np.inf


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 9), st.integers(1, 12), st.integers(1, 15),
       st.integers(0, 2**31 - 1))
def test_top_cells_are_the_best_counts_of_each_rotation(nrot, h, w, k, seed):
    acc = np.random.default_rng(seed).integers(0, 6, (nrot, h, w)).astype(np.uint8)
    sc, iy, ix = top_cells(acc, k)
    kk = min(k, h * w)
    assert sc.shape == iy.shape == ix.shape == (nrot, kk)
    for r in range(nrot):
        assert np.array_equal(acc[r, iy[r], ix[r]], sc[r])           # counts where they say
        assert len({(a, b) for a, b in zip(iy[r], ix[r], strict=True)}) == kk       # distinct cells
        assert sorted(sc[r]) == sorted(np.sort(acc[r].ravel())[-kk:])  # the k best


def test_phase_stack_reads_the_mask_at_a_stride_with_the_tight_count_in_the_low_bits():
    # one wall along y = 0 from x = 0 to 4; wide 0.41 m, tight 0.2 m: a pixel on the wall
    # holds 16 + 1, one 0.3 m off it 16, one 1 m off it 0; the phase (py, px) at (j, i)
    # is the padded mask's pixel (py + j * step, px + i * step)
    f = DistanceField(_segment_map([(0, 0, 4, 0), (0, 3, 4, 3)]), 0.05)
    step = 6
    pad, stack = f.phase_stack(0.41, step, tight=0.2)
    assert stack.dtype == np.uint8 and stack.shape[0] == step * step

    def at(x: float, y: float) -> int:
        # the padded mask's pixel of world point (x, y), read through its phase
        px = int(round((x - f.lo[0]) / f.res)) + pad
        py = int(round((y - f.lo[1]) / f.res)) + pad
        return int(stack[(py % step) * step + px % step, py // step, px // step])

    assert at(2.0, 0.0) == 17 and at(2.0, 0.3) == 16 and at(2.0, 1.0) == 0
    assert at(1.0, 3.0) == 17 and at(-3.0, 0.0) == 0
    # without the tight count: a plain 0/1 mask
    _, plain = f.phase_stack(0.41, step)
    assert set(np.unique(plain).tolist()) <= {0, 1}
    assert int(plain.sum()) == np.count_nonzero(stack >= 16)


def _rooms_map() -> tuple[LineMap, list]:
    """A 5 x 4 grid of rooms 9 m apart, no two alike (their sizes and a cabinet's place
    differ): a map of about 45 x 36 m, whose sweep grid is big enough to be swept coarse to
    fine."""
    walls = []
    for i in range(5):
        for j in range(4):
            x0, y0 = 9.0 * i, 9.0 * j
            x1, y1 = x0 + 5.0 + 0.4 * i, y0 + 4.0 + 0.5 * j
            walls += [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]
            c = 0.3 + 0.2 * (i + 2 * j) % 3.0
            walls.append((x0 + c, y0 + 1.0, x0 + c + 1.2, y0 + 1.0 + 0.1 * j))
    return _segment_map(walls), walls


@pytest.mark.parametrize("tight", [None, 0.2])
@pytest.mark.parametrize("f", [2, 3, 5])
def test_coarse_to_fine_sweep_finds_the_best_positions(f, tight):
    # counting only the coarse cells whose bound reaches the k-th best count gives the k
    # best positions of every rotation that counting every position gives, ties settled by
    # the same byte per position; in the band, and (no band) over the whole grid
    m, walls = _rooms_map()
    field = DistanceField(m, 0.05)
    p = np.array([20.7, 11.6, 0.4])
    seg = segments_from_scan(scan(world(walls), p, n=360, fov=2 * np.pi, sigma=0.005, seed=2))
    pts = seg.points[:: max(1, len(seg.points) // 15)][:15]
    rots = np.radians(np.arange(0.0, 360.0, 7.5))
    step, k = 5, 20
    pad, stack = field.phase_stack(0.38, step, tight)
    c, s = np.cos(rots)[:, None], np.sin(rots)[:, None]
    ox = np.round((c * pts[:, 0] - s * pts[:, 1]) / 0.05).astype(np.int64) + pad
    oy = np.round((s * pts[:, 0] + c * pts[:, 1]) / 0.05).astype(np.int64) + pad
    ny, nx = field.grid_shape(step)
    band = field.grid_dist(step) <= 4.0
    for window in [(0, 0, ny, nx), (7, 11, ny - 20, nx - 31)]:
        y0, x0, h, w = window
        acc = window_counts(stack, oy, ox, step, window).astype(np.int64)
        for b in (None, band):
            full = acc * b[y0: y0 + h, x0: x0 + w] if b is not None else acc
            key = (full << 8) | tie_noise(np.arange(len(rots))[:, None, None],
                                          np.arange(h)[None, :, None] + y0,
                                          np.arange(w)[None, None, :] + x0)
            sc, iy, ix = coarse_to_fine(field, stack, 0.38, tight, step, f, oy, ox, window,
                                        b, k)
            ri = np.arange(len(rots))[:, None]
            assert np.array_equal(sc, full[ri, iy, ix])           # counts where they say
            best = np.sort(key.reshape(len(rots), -1), axis=1)[:, -k:]
            assert np.array_equal(np.sort(key[ri, iy, ix], axis=1), best)


def test_relocalisation_swept_coarse_to_fine_finds_the_pose():
    m, walls = _rooms_map()
    field = DistanceField(m, 0.05)
    P = replace(RelocParams(), sweep_direct=0)
    for k, p in enumerate([(20.7, 11.6, 0.4), (29.2, 20.1, -2.0), (2.5, 2.3, 2.9)]):
        seg = segments_from_scan(scan(world(walls), p, n=360, fov=2 * np.pi, sigma=0.005,
                                      seed=k))
        r = relocalize(m, seg, field, P)
        assert r.found
        et, er = _pose_err(r.pose, p)
        assert et < 0.05 and er < 0.5, (p, r.pose)


def test_plain_count_on_the_packed_bits_is_the_distance_fields():
    # the inlier count read from the packed bits equals the one read from the distance field
    # itself, for poses all over the map and beyond its edge
    m, _ = _rooms_map()
    field = DistanceField(m, 0.05)
    rng = np.random.default_rng(4)
    pts = rng.uniform(-6, 6, (40, 2))
    T = rng.uniform(field.lo - 5, field.lo + field.size * field.res + 5, (500, 2))
    th = rng.uniform(-np.pi, np.pi, 500)
    for inlier in (0.12, 0.2, 0.5):
        got = inlier_scores(field, pts, T, th, inlier)
        c, s = np.cos(th)[:, None], np.sin(th)[:, None]
        gx = c * pts[:, 0] - s * pts[:, 1] + T[:, :1]
        gy = s * pts[:, 0] + c * pts[:, 1] + T[:, 1:]
        want = np.mean(field.lookup_xy(gx, gy) < inlier, axis=1)
        assert np.array_equal(got, want) and 0.0 < want.mean() < 0.5


@pytest.mark.parametrize("k", [1, 20, 120, 5000])
def test_best_distinct_candidates_without_counting_every_one(k):
    # the k best candidates one per cell, counts stopped early where they cannot reach the
    # bar, are those of counting every candidate and ranking them (ties by index): around
    # the true pose (near-duplicates in one cell, equal counts), elsewhere and off the map
    m, walls = _rooms_map()
    field = DistanceField(m, 0.05)
    p = np.array([20.7, 11.6, 0.4])
    seg = segments_from_scan(scan(world(walls), p, n=360, fov=2 * np.pi, sigma=0.005, seed=3))
    rng = np.random.default_rng(5)
    near = p + rng.normal(0, [0.1, 0.1, 0.03], (3000, 3))
    near[::3] = np.round(near[::3] / 0.05) * 0.05        # exact repeats: tied counts
    wide = np.column_stack([rng.uniform(field.lo - 3, field.lo + field.size * field.res + 3,
                                        (6000, 2)), rng.uniform(-np.pi, np.pi, 6000)])
    cand = rng.permutation(np.concatenate([near, wide]))
    T, th = cand[:, :2], cand[:, 2]
    for inlier, n in [(0.2, 40), (0.12, 40), (0.2, 6)]:     # 6 points: many equal counts
        pts = seg.points[np.linspace(0, len(seg.points) - 1, n).astype(int)]
        order = np.argsort(-inlier_scores(field, pts, T, th, inlier), kind="stable")
        want = distinct_cells(T, th, order, 0.3, np.radians(3.0), k)
        got = best_distinct(field, pts, T, th, inlier, 0.3, np.radians(3.0), k)
        assert np.array_equal(got, want) and len(got) == min(k, len(
            np.unique(np.floor(np.column_stack([T / 0.3, np.mod(th, 2 * np.pi) / np.radians(
                3.0)])), axis=0)))


def test_a_hint_keeps_the_sweeps_to_its_neighbourhood():
    # 24 rooms alike (ROOM repeated 9 m apart) and a cluttered scan (its one segment is not
    # in the map, so only the sweeps can place it): over the whole map its pose is one of 24
    # equally good ones; near a hint in the right room the sweeps read only there (every
    # candidate inside the hint's box, at the hint's rotations) and the scan is placed
    walls = [(x1 + 9.0 * i, y1 + 9.0 * j, x2 + 9.0 * i, y2 + 9.0 * j)
             for i in range(6) for j in range(4) for x1, y1, x2, y2 in ROOM]
    m = _segment_map(walls)
    field = DistanceField(m, 0.05)
    p = np.array([-0.5 + 27.0, 0.8 + 9.0, 1.1])
    seg = _cluttered_scan(np.array([-0.5, 0.8, 1.1]))   # ROOM's scan: the same in every room
    hint = (p + np.array([0.6, -0.5, 0.15]), 2.0, 0.52)
    P = RelocParams()
    rots = np.radians(np.arange(0.0, 360.0, 10.0))
    T, th = correlative_sweep(field, seg.points, rots, P, near=hint)
    assert len(T) and np.all(np.abs(T - hint[0][:2]) <= 2.0 + P.sweep_grid + 1e-9)
    reach = reach_bound(seg.points, P, 0.05)
    T, th = fallback_sweep(field, seg.points, P, reach, near=hint)
    assert len(T) and np.all(np.abs(wrap(th - hint[0][2])) < 0.52 + np.radians(3.0) + 1e-9)
    r = relocalize(m, seg, field, P, near=hint)
    assert r.found and _pose_err(r.pose, p)[0] < 0.05 and _pose_err(r.pose, p)[1] < 0.5
    # whole map: every room fits alike, so the answer cannot name the right one
    whole = relocalize(m, seg, field, P)
    assert whole.found and sum(_pose_err(h.pose, p)[0] > 1.0 for h in whole.hypotheses) >= 2
