"""The global line map: merge, extend, count, age out, dedupe, follow re-optimised poses;
map JSON round trip and rejection of malformed files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from cgamap.mapping.linemap import LineMap, MapParams, age_out, copies, dedupe, integrate, refresh
from cgamap.mapping.mapio import MapFormatError, load_map, map_to_json, save_map
from cgamap.mapping.segments import Segments, segments_from_scan
from synth2d import ROOM, scan, world


def _seg(a, b, n=20) -> Segments:
    a, b = np.atleast_2d(np.asarray(a, float)), np.atleast_2d(np.asarray(b, float))
    k = len(a)
    # moments of n points spread evenly between a and b
    t = np.linspace(0, 1, n)
    pts = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
    c = pts.mean(1)
    d = pts - c[:, None, :]
    S = np.einsum("kni,knj->kij", d, d)
    return Segments(a, b, np.full(k, n), np.zeros(k), c, S, np.zeros((k, 2, 2)))


def test_same_wall_twice_is_one_segment_with_two_observations():
    m = LineMap()
    integrate(m, _seg([0, 0], [4, 0]), 0)
    integrate(m, _seg([0.1, 0.01], [4.1, 0.01]), 1)
    assert len(m) == 1 and m.n_obs[0] == 2
    assert m.a[0][0] == pytest.approx(0.0, abs=1e-6) and m.b[0][0] == pytest.approx(4.1, abs=1e-6)
    assert abs(m.a[0][1] - 0.005) < 1e-3  # refitted between the two observations


def test_pieces_extend_and_bridge():
    m = LineMap()
    integrate(m, _seg([[0, 0], [3, 0]], [[2, 0], [5, 0]]), 0)  # a gap of 1 m: two pieces
    assert len(m) == 2
    integrate(m, _seg([1.5, 0.0], [3.5, 0.0]), 1)  # an observation across the gap joins them
    assert len(m) == 1
    assert m.length[0] == pytest.approx(5.0, abs=1e-6) and m.n_obs[0] == 3


def test_perpendicular_and_parallel_walls_stay_apart():
    m = LineMap()
    integrate(m, _seg([[0, 0], [0, 0.5]], [[4, 0], [4, 0.5]]), 0)   # two walls 0.5 m apart
    integrate(m, _seg([[2, -2]], [[2, -0.5]]), 1)                    # a perpendicular one
    assert len(m) == 3


def test_not_a_line_is_not_fused():
    m = LineMap()
    integrate(m, _seg([0, 0], [4, 0]), 0)
    # within the gates (4 deg, 0.1 m) but the joint fit would not be a line
    integrate(m, _seg([0, 0.09], [4, 0.37]), 1, MapParams(max_residual=0.02))
    assert len(m) == 2


def test_a_wall_thickened_by_its_observations_still_takes_more():
    # a wall seen from poses a few cm apart: its fused segment is 4.5 cm thick (RMS), past
    # the 3 cm a fusion may add.  A later observation on its line is the same wall, not a
    # copy beside it (the thickness is the wall's past, not what this fusion adds)
    m = LineMap()
    for k, y in enumerate((0.045, -0.045, 0.045, -0.045)):
        integrate(m, _seg([0, y], [4, y]), k, MapParams(max_residual=0.08))
    assert len(m) == 1 and np.sqrt(np.linalg.eigvalsh(m.scatter[0])[0] / m.n_pts[0]) > 0.04
    for k in range(4, 10):
        integrate(m, _seg([0.5, 0.0], [3.5, 0.0]), k)
        assert len(m) == 1 and m.n_obs[0] == k + 1


def test_a_chain_of_candidates_fuses_its_lines_not_its_neighbours():
    # two pieces of one wall and a desk edge 6 cm in front of it, overlapping both: within
    # the merge gates (0.10 m) every pair is a candidate, so all three form one component.
    # The wall's pieces join; the desk, 6 cm off, stays apart (judged whole, the component
    # was refused and the wall stayed in two pieces)
    m = LineMap()
    m.append(_seg([[0, 0], [2.1, 0], [1.0, 0.06]], [[2.0, 0], [4, 0], [3.0, 0.06]]), 0)
    assert dedupe(m) == 1 and len(m) == 2
    wall = int(np.argmax(m.length))
    assert m.length[wall] == pytest.approx(4.0, abs=1e-6) and abs(m.a[wall, 1]) < 1e-9
    # an observation along the desk joins the desk
    integrate(m, _seg([1.2, 0.06], [2.8, 0.06]), 1)
    assert len(m) == 2 and m.n_obs[1 - wall] == 2


def test_copies_are_overlapping_near_collinear_pairs():
    a = np.array([[0, 0], [1, 0.02], [0, 1], [5, 0], [2, -0.05], [3, 0]], float)
    b = np.array([[4, 0], [3, 0.02], [0, 3], [6, 0], [3, -0.05], [3, 1]], float)
    # 0 and 1: one wall twice, 2 cm apart and overlapping; 2 and 5: perpendicular to it;
    # 3: on its line but beyond its end; 4: 5 cm off
    assert copies(a, b) == 2
    assert copies(a, b, dist=0.06) == 3           # 4 joins: a copy of 0 within 6 cm
    assert copies(a, b, chunk=2) == copies(a, b)  # chunked rows, same count
    assert copies(a[[0, 2, 3]], b[[0, 2, 3]]) == 0


def test_age_out_and_dedupe():
    m = LineMap()
    integrate(m, _seg([0, 0], [4, 0]), 0)
    integrate(m, _seg([0, 3], [0.4, 3]), 0)          # short, seen once
    integrate(m, _seg([0, 0], [4, 0]), 1)
    for k in range(2, 20):
        integrate(m, _seg([0, 0], [4, 0]), k)
        age_out(m, k)
    assert len(m) == 1 and m.n_obs[0] == 20
    # two coinciding segments (as after a loop closure) are fused by dedupe
    m2 = LineMap()
    m2.append(_seg([[0, 0], [1, 0.01]], [[4, 0], [5, 0.01]]), 0)
    assert dedupe(m2) == 1 and len(m2) == 1


def test_contributions_grow_in_place_and_earlier_views_stay():
    """Contribution columns grow into spare room (no copy per scan), across subsets that
    replace or share them; what was read before an append is never overwritten."""
    m, want = LineMap(), []
    for k in range(60):
        seg = _seg([[k, 0.0], [k, 5.0]], [[k + 0.5, 0.0], [k, 6.0]])
        m.append(seg, k)
        m.add_contributions(np.arange(len(m) - 2, len(m)), k, seg)
        want += [(k, len(m) - 2), (k, len(m) - 1)]
        if k == 20:
            early = m.c_node
            early_copy = early.copy()
        if k in (30, 45):  # a subset sharing the rows, then one dropping some
            keep = np.ones(len(m), bool)
            if k == 45:
                keep[:4] = False
                want = [(n, s - 4) for n, s in want if s >= 4]
            m2 = m.subset(keep)
            m.a, m.b, m.c_seg, m.c_node = m2.a, m2.b, m2.c_seg, m2.c_node
            m.c_n, m.c_cent, m.c_scat, m.c_a, m.c_b = m2.c_n, m2.c_cent, m2.c_scat, m2.c_a, \
                m2.c_b
            m.n_pts, m.centroid, m.scatter = m2.n_pts, m2.centroid, m2.scatter
            m.n_obs, m.created, m.last_seen = m2.n_obs, m2.created, m2.last_seen
    assert list(zip(m.c_node.tolist(), m.c_seg.tolist(), strict=True)) == want
    assert np.array_equal(early, early_copy)
    assert len(m.c_a) == len(m.c_scat) == len(want) and m.c_n.dtype == float
    # a shallow copy shares the buffers' bookkeeping: each still appends its own rows
    import copy

    other = copy.copy(m)
    seg = _seg([[0.0, 9.0]], [[1.0, 9.0]])
    m.add_contributions(np.array([0]), 100, seg)
    other.add_contributions(np.array([1]), 200, seg)
    assert m.c_node[-1] == 100 and other.c_node[-1] == 200
    assert len(m.c_node) == len(other.c_node) == len(want) + 1


def test_refresh_follows_new_poses():
    m = LineMap()
    w = world(ROOM)
    poses = np.array([[0.0, 0.0, 0.0], [0.5, 0.2, 0.3]])
    for i, p in enumerate(poses):
        seg = segments_from_scan(scan(w, p, n=720, fov=2 * np.pi))
        integrate(m, seg.transformed(*p), i, seg_l=seg, node=i)
    before = m.a.copy()
    assert len(m) == 4 and np.all(m.n_obs == 2)
    refresh(m, poses)                       # same poses: the same map
    assert np.allclose(np.sort(m.a, 0), np.sort(before, 0), atol=1e-6)
    refresh(m, poses + [1.0, 0.0, 0.0])     # everything moved by 1 m
    assert np.allclose(np.sort(m.a[:, 0]), np.sort(before[:, 0]) + 1.0, atol=1e-6)


def _room_map() -> LineMap:
    m = LineMap()
    seg = segments_from_scan(scan(world(ROOM), (0.0, 0.0, 0.0), n=720, fov=2 * np.pi))
    integrate(m, seg, 0)
    return m


def test_json_round_trip(tmp_path):
    m = _room_map()
    p = tmp_path / "map.json"
    save_map(m, p, {"note": "room"})
    back = load_map(p)
    assert np.allclose(back.a, m.a, atol=1e-5) and np.allclose(back.b, m.b, atol=1e-5)
    assert np.array_equal(back.n_obs, m.n_obs)
    assert back.metadata["note"] == "room"
    doc = json.loads(p.read_text())
    assert doc["version"] == 1 and "point_pair" in doc["segments"][0]["cga"]
    assert set(doc["segments"][0]["cga"]["sphere"]) <= {"e1", "e2", "e3", "e+", "e-"}


@pytest.mark.parametrize("mutate, message", [
    (lambda d: d.update(format="other"), "format"),
    (lambda d: d.update(version=99), "unsupported version"),
    (lambda d: d["segments"][1].update(a=[1.0]), r"segments\[1\]\.a"),
    (lambda d: d["segments"][0].update(n_obs=0), r"segments\[0\]\.n_obs"),
    (lambda d: d["segments"][2].update(b=d["segments"][2]["a"]), "coincide"),
    (lambda d: d["segments"][0]["cga"]["point_pair"].update({"e12": 123.0}), "does not match"),
    (lambda d: d["segments"][0]["cga"]["point_pair"].update({"e9": 1.0}), "unknown blade"),
    (lambda d: d.update(segments={}), "segments must be a list"),
])
def test_malformed_files_are_rejected(tmp_path, mutate, message):
    doc = map_to_json(_room_map())
    mutate(doc)
    p = tmp_path / "bad.json"
    p.write_text(json.dumps(doc))
    with pytest.raises(MapFormatError, match=message) as exc:
        load_map(p)
    assert "bad.json" in str(exc.value)


def test_not_json_and_nan(tmp_path):
    p = tmp_path / "x.json"
    p.write_text("{not json")
    with pytest.raises(MapFormatError, match="not JSON"):
        load_map(p)
    doc = map_to_json(_room_map())
    text = json.dumps(doc).replace(str(doc["segments"][0]["a"][0]), "NaN", 1)
    p.write_text(text)
    with pytest.raises(MapFormatError, match="finite"):
        load_map(p)
    with pytest.raises(MapFormatError, match="cannot read"):
        load_map(tmp_path / "missing.json")


def test_components_of_a_small_graph():
    from cgamap.mapping.linemap import _components

    # a chain 9-4-7-2 given out of order (labels must travel 3 edges), a pair 5-8, and 3-3
    u = np.array([7, 4, 5, 7, 3])
    v = np.array([2, 9, 8, 4, 3])
    member, group, n = _components(u, v)
    assert n == 3
    got = [member[group == g].tolist() for g in range(n)]
    assert got == [[2, 4, 7, 9], [3], [5, 8]]  # ascending, ordered by smallest node
    assert _components(np.zeros(0, int), np.zeros(0, int))[2] == 0


def test_a_long_segment_seen_once_goes_when_the_next_scans_looked_from_nearby():
    """Seen once, a segment of any length goes once the robot went at most age_travel in
    the age_scans scans since (scanning densely, they saw its place and not it); after a
    longer way it stays, as short ones stay only while young (MapParams.age_travel)."""
    P = MapParams(age_scans=12, age_min_length=0.6, age_travel=1.0)
    for step, kept in ((0.05, False), (0.5, True)):
        m = LineMap()
        integrate(m, _seg([0, 3], [1.5, 3]), 0)           # seen once, 1.5 m long
        travel = step * np.arange(30)
        for k in range(1, 30):
            integrate(m, _seg([0, 0], [4, 0]), k)
            age_out(m, k, P, travel[:k + 1])
        assert (len(m) == 2) == kept, step
    # without the travel (or a segment from before this run), length alone decides
    m = LineMap()
    integrate(m, _seg([0, 3], [1.5, 3]), 0)
    m.created[:] = -5
    for k in range(1, 30):
        age_out(m, k, P, 0.05 * np.arange(k + 1))
    assert len(m) == 1
    assert age_out(m, 40, P) == 0 and len(m) == 1


def test_a_segment_seen_only_by_a_few_of_the_scans_just_after_it_goes():
    """Seen at most age_seen times, all within the age_scans scans after it appeared, from
    nearly one place (age_travel, age_turn): dropped.  Seen by more of them, seen again
    later, or with the robot turning away meanwhile: kept."""
    P = MapParams(age_scans=12, age_travel=1.0, age_seen=3, age_turn=0.5)

    def run(sightings, turn_per_scan=0.0) -> bool:
        m = LineMap()
        travel, turned = 0.05 * np.arange(40), turn_per_scan * np.arange(40)
        for k in range(40):
            integrate(m, _seg([0, 0], [4, 0]), k)
            if k in sightings:
                integrate(m, _seg([0, 3], [1.5, 3]), k)
            age_out(m, k, P, travel[:k + 1], turned[:k + 1])
        return len(m) == 2

    assert not run({0, 1, 2})
    assert run({0, 1, 2, 3})                   # four times: a wall
    assert run({0, 1, 30})                     # seen again later
    assert run({0, 1, 2}, turn_per_scan=0.1)   # 1.2 rad in 12 scans: it left the view
    assert not run({0, 1, 2}, turn_per_scan=0.03)  # 0.36 rad: still in view


def test_a_glimpse_aged_out_hands_its_contributions_to_retired():
    """The contributions of a segment dropped as a glimpse (seen only by the few scans just
    after it appeared) go to ``retired``, for a loop closure's submap; those of a short
    piece seen once, and of one the laser saw through, do not."""
    P = MapParams(age_scans=12, age_travel=1.0, age_seen=3, age_turn=0.5)
    m, retired = LineMap(), []
    wall = _seg([0, 0], [4, 0])
    for k in range(20):
        integrate(m, wall, k, P, seg_l=wall, node=k)
        if k in (1, 2, 3):
            # the same 1.5 m glimpse three times, in the laser frame shifted by the node
            g = _seg([0, 3], [1.5, 3])
            integrate(m, g, k, P, seg_l=_seg([k, 3], [k + 1.5, 3]), node=k)
        age_out(m, k, P, 0.05 * np.arange(k + 1), np.zeros(k + 1), retired)
    assert len(m) == 1
    assert len(retired) == 1
    nodes, a, b = retired[0]
    np.testing.assert_array_equal(nodes, [1, 2, 3])
    np.testing.assert_allclose(a, [[1, 3], [2, 3], [3, 3]])
    np.testing.assert_allclose(b, [[2.5, 3], [3.5, 3], [4.5, 3]])
    # a seen-once short piece goes as before, and is not retired
    short, retired = LineMap(), []
    for k in range(20):
        integrate(short, wall, k, P, seg_l=wall, node=k)
        if k == 1:
            integrate(short, _seg([0, 3], [0.3, 3]), k, P, seg_l=_seg([0, 3], [0.3, 3]), node=k)
        age_out(short, k, P, 0.05 * np.arange(k + 1), np.zeros(k + 1), retired)
    assert len(short) == 1 and retired == []
    # a glimpse the laser also saw through has gone from the world: not retired
    seen_through, retired = LineMap(), []
    for k in range(20):
        integrate(seen_through, wall, k, P, seg_l=wall, node=k)
        if k in (1, 2, 3):
            g = _seg([0, 3], [1.5, 3])
            integrate(seen_through, g, k, P, seg_l=g, node=k)
        if k == 14:  # judged from 14 on (1 + age_scans), seen through by then
            seen_through.through[seen_through.length < 2] = P.clear.scans
        age_out(seen_through, k, P, 0.05 * np.arange(k + 1), np.zeros(k + 1), retired)
    assert len(seen_through) == 1 and retired == []
