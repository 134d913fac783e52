"""Pose correction (eqs. 10-11) and the pose graph: known motions are recovered."""

from __future__ import annotations

import numpy as np
import pytest
from cgamap.mapping.correction import CorrectionParams, _inverse3, correct_batch, correct_pose
from cgamap.mapping.evaluation import align_rigid_2d, apply_pose, ate, rpe
from cgamap.mapping.matching import LineIndex
from cgamap.mapping.posegraph import PoseGraph, relative, wrap
from cgamap.mapping.segments import segments_from_scan
from cgamap.mapping.slam2d import compose
from hypothesis import given, settings
from hypothesis import strategies as st
from synth2d import L_CORNER, ROOM, scan, world

TRUE = np.array([0.4, -0.3, 0.25])


def _room_map():
    w = world(ROOM)
    seg = segments_from_scan(scan(w, (0.0, 0.0, 0.0), n=720, fov=2 * np.pi))
    return w, seg


@settings(max_examples=25, deadline=None)
@given(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-0.08, 0.08))
def test_known_motion_recovered_from_segments(dx, dy, dth):
    """Property: the map is a scan's segments moved by a known pose; starting from a wrong
    guess, the correction finds that pose."""
    _, seg = _room_map()
    glob = seg.transformed(*TRUE)
    guess = TRUE + [dx, dy, dth]
    c = correct_pose(seg, glob.a, glob.b, guess, step=10.0)  # a weak odometry prior
    assert np.allclose(c.pose[:2], TRUE[:2], atol=2e-3)
    assert abs(wrap(c.pose[2] - TRUE[2])) < 1e-3
    assert c.matched_fraction > 0.9 and c.rms < 1e-3


def test_one_problem_and_a_batch_solve_alike():
    """The compiled adjugate inverse is LAPACK's, and a problem solved alone gives what it
    gives inside a batch."""
    rng = np.random.default_rng(3)
    A = rng.normal(size=(5, 3, 3))
    H = A @ np.swapaxes(A, 1, 2) + np.eye(3) * 1e-3 + np.diag([1e4, 1e4, 1e5])
    g = rng.normal(size=(5, 3)) * 100.0
    want = np.linalg.solve(H, g[..., None])[..., 0]
    assert np.allclose((_inverse3(H) @ g[..., None])[..., 0], want, rtol=1e-10, atol=0)
    assert np.allclose(_inverse3(H), np.linalg.inv(H), rtol=1e-10, atol=0)
    _, seg = _room_map()
    idx = LineIndex.of(np.repeat(seg.a[None], 3, 0), np.repeat(seg.b[None], 3, 0))
    guess = np.array([[0.1, -0.05, 0.03], [-0.1, 0.08, -0.04], [0.0, 0.1, 0.02]])
    both = correct_batch(np.repeat(seg.a[None], 3, 0), np.repeat(seg.b[None], 3, 0), idx,
                         guess, 10.0)
    for i in range(3):
        one = correct_batch(seg.a[None], seg.b[None], LineIndex.of(seg.a[None], seg.b[None]),
                            guess[i:i + 1], 10.0)
        assert np.allclose(one.pose[0], both.pose[i], atol=1e-9)
        assert np.abs(one.pose[0]).max() < 2e-3  # the walls win over the prior


def test_scan_from_another_pose_is_located():
    w, seg0 = _room_map()
    pose = np.array([0.6, 0.3, 0.4])
    seg1 = segments_from_scan(scan(w, pose, n=720, fov=2 * np.pi, sigma=0.005))
    c = correct_pose(seg1, seg0.a, seg0.b, pose + [0.1, -0.12, -0.05], step=10.0)
    assert np.hypot(*(c.pose[:2] - pose[:2])) < 0.02
    assert abs(wrap(c.pose[2] - pose[2])) < np.deg2rad(0.5)
    assert np.all(np.linalg.eigvalsh(c.cov) > 0)


def test_corridor_direction_is_held_by_the_prior():
    # only one wall direction: translation along it must stay at the prediction
    w = world([(-10, -1, 10, -1), (-10, 1, 10, 1)])
    seg = segments_from_scan(scan(w, (0.0, 0.0, 0.0)))
    pred = np.array([0.3, 0.05, 0.0])
    c = correct_pose(seg, seg.a, seg.b, pred, step=1.0)
    assert c.pose[0] == pytest.approx(0.3, abs=1e-6)
    assert c.pose[1] == pytest.approx(0.0, abs=0.01)  # the walls win over the prior
    assert c.cov[0, 0] > 5 * c.cov[1, 1]  # the covariance says which way is unknown


def test_no_map_keeps_prediction():
    seg = segments_from_scan(scan(world(L_CORNER), (0.0, 0.0, 0.0)))
    c = correct_pose(seg, np.zeros((0, 2)), np.zeros((0, 2)), TRUE)
    assert np.allclose(c.pose, TRUE) and c.matched_fraction == 0.0


def test_pose_graph_closes_a_square_loop():
    rng = np.random.default_rng(1)
    true = [np.zeros(3)]
    for k in range(39):
        true.append(compose(true[-1], [1.0, 0.0, np.pi / 2 if k % 10 == 9 else 0.0]))
    true = np.array(true)
    g = PoseGraph()
    g.add_node(true[0])
    est = true[0].copy()
    info = np.diag([1 / 0.02 ** 2, 1 / 0.02 ** 2, 1 / 0.01 ** 2])
    for k in range(1, 40):
        z = relative(true[k - 1], true[k]) + rng.normal(0, [0.02, 0.02, 0.01])
        est = compose(est, z)
        g.add_node(est)
        g.add_edge(k - 1, k, z, info)
    before = ate(np.array(g.poses), true)["ate_trans_m"]
    g.add_edge(0, 39, relative(true[0], true[39]), info * 4, loop=True)
    g.optimize()
    after = ate(np.array(g.poses), true)["ate_trans_m"]
    assert after < 0.5 * before
    assert np.allclose(g.poses[0], true[0])  # the first node is held


def _square_loop_graph(seed: int = 1) -> tuple[PoseGraph, np.ndarray]:
    rng = np.random.default_rng(seed)
    true = [np.zeros(3)]
    for k in range(59):
        true.append(compose(true[-1], [1.0, 0.0, np.pi / 2 if k % 10 == 9 else 0.0]))
    g = PoseGraph([np.zeros(3)])
    info = np.diag([1 / 0.02 ** 2, 1 / 0.02 ** 2, 1 / 0.01 ** 2])
    for k in range(1, 60):
        z = relative(true[k - 1], true[k]) + rng.normal(0, [0.02, 0.02, 0.01])
        g.add_node(compose(g.poses[-1], z))
        g.add_edge(k - 1, k, z, info)
    # closures from the last lap to the first and to the middle of the run
    for i, j in [(0, 40), (10, 50), (25, 55), (30, 59)]:
        g.add_edge(i, j, relative(true[i], true[j]), info * 4, loop=True)
    return g, np.array(true)


@pytest.mark.parametrize("window", [0, 35])
def test_a_closure_judged_wrong_is_not_trusted_again(window):
    """The graduated first iterations trust new closures only: a wrong one (1 m off along
    the square's side) that a solve has already rejected does not drag the next solve's
    graph away and back (the online mapper solves again at every disagreeing closure)."""
    g, true = _square_loop_graph()
    info = np.diag([1 / 0.02 ** 2, 1 / 0.02 ** 2, 1 / 0.01 ** 2]) * 4
    wrong = compose(relative(true[5], true[45]), [1.0, 0.0, 0.0])
    g.add_edge(5, 45, wrong, info, loop=True)
    g.optimize(iterations=30, free_from=window)  # converged
    solved = np.array(g.poses)
    miss = relative(solved[5], solved[45]) - wrong
    assert np.hypot(miss[0], miss[1]) > 0.8  # the wrong closure was rejected
    again = PoseGraph([p.copy() for p in solved], g.ei, g.ej, g.z, g.info, g.loop)
    got = again.optimize(free_from=window, judged=len(g.ei))
    assert got["iterations"] <= 4
    assert np.abs(np.array(again.poses) - solved).max() < 1e-4
    # all trusted again (the old behaviour): dragged off, then back over many iterations
    trusting = PoseGraph([p.copy() for p in solved], g.ei, g.ej, g.z, g.info, g.loop)
    assert trusting.optimize(free_from=window)["iterations"] > got["iterations"]


def test_windowed_solve_is_the_full_solve_with_the_old_nodes_held(monkeypatch):
    import cgamap.mapping.posegraph as pg

    g, _ = _square_loop_graph()
    full = PoseGraph([p.copy() for p in g.poses], g.ei, g.ej, g.z, g.info, g.loop)
    before = np.array(g.poses)
    sizes = []
    real_solve = pg.solve_normal
    monkeypatch.setattr(pg, "solve_normal", lambda H, b, n: sizes.append(len(b)) or
                        real_solve(H, b, n))
    got = g.optimize(free_from=35)
    # the held boundary (nodes 0, 10, 25, 30 and 34, tied to the window) is no unknown: a
    # window tied to every earlier lap would otherwise carry thousands of them
    assert set(sizes) == {3 * 25}
    full.optimize(fixed=list(range(35)))
    after = np.array(g.poses)
    assert np.array_equal(after[:35], before[:35])        # the old nodes did not move
    assert np.abs(after[35:] - before[35:]).max() > 0.05  # the window did
    assert np.allclose(after, np.array(full.poses), atol=1e-5)
    assert got["nodes"] == 25


def test_windowed_solve_of_a_window_without_edges_changes_nothing():
    g = PoseGraph([np.zeros(3), np.ones(3)], [0], [1], [np.zeros(3)], [np.eye(3)], [False])
    g.poses.append(np.full(3, 2.0))   # a node no edge reaches
    assert g.optimize(free_from=2)["iterations"] == 0
    assert np.allclose(g.poses[2], 2.0)


def test_graph_columns_are_used_as_lists_and_stay_compact():
    """The graph's columns do what the lists they replaced did (append, index, assign,
    delete a slice, copy) and hold each edge in ~113 bytes, not a Python object per value."""
    from cgamap.mapping.posegraph import Column

    g, ref = PoseGraph(), {"ei": [], "ej": [], "z": [], "info": [], "loop": []}
    for k in range(300):
        g.add_node([k, 0.0, 0.0])
    for k in range(1000):
        e = (k % 299, k % 299 + 1, [k, 1.0, 0.5], np.eye(3) * k, k % 3 == 0)
        g.add_edge(*e[:4], loop=e[4])
        for name, v in zip(ref, e, strict=True):
            ref[name].append(np.asarray(v))
    copy = g.copy()
    del g.ei[100:250], g.info[100:250], ref["ei"][100:250], ref["info"][100:250]
    g.info[7] = g.info[7] * 0.5
    ref["info"][7] = ref["info"][7] * 0.5
    assert len(g.ei) == 850 and np.array_equal(np.asarray(g.ei), ref["ei"])
    assert np.array_equal(np.asarray(g.info), ref["info"]) and g.info[-1][0, 0] == 999
    assert len(copy.ei) == 1000 and copy.info[7][0, 0] == 7.0  # the copy is its own
    assert np.array_equal(g.z[[3, 5]], [[3, 1, 0.5], [5, 1, 0.5]]) and g.loop[3]
    assert list(g.poses[-1]) == [299, 0, 0] and isinstance(g.poses, Column)
    g.poses = [np.zeros(3)] * 4  # assigned lists become columns
    assert isinstance(g.poses, Column) and len(g.poses) == 4
    per_edge = sum(getattr(copy, n)._buf[:1].nbytes for n in ("ei", "ej", "z", "info", "loop"))
    assert per_edge == 8 + 8 + 24 + 72 + 1


def test_ate_is_zero_after_a_rigid_motion_and_rpe_sees_steps():
    t = np.linspace(0, 10, 60)
    ref = np.column_stack([t, np.sin(t), np.cos(t)])
    moved = apply_pose((1.0, -2.0, 0.7), ref)
    T = align_rigid_2d(moved, ref)
    assert np.allclose(apply_pose(T, moved), ref, atol=1e-9)
    assert ate(moved, ref)["ate_trans_m"] < 1e-9
    assert rpe(moved, ref)["rpe_trans_m"] < 1e-9
    bumped = ref.copy()
    bumped[30:, 1] += 0.1
    assert rpe(bumped, ref)["rpe_trans_m"] > 0.01


def test_normal_equations_are_the_edges_jacobians_summed():
    """H = sum J^T W J and g = sum J^T W e over the edges, J by finite differences of the
    residual: every 3x3 block where it belongs, repeated edges between two nodes added."""
    rng = np.random.default_rng(7)
    n = 6
    X = rng.normal(0, 2, (n, 3))
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 4), (4, 0), (2, 5), (2, 5), (5, 1)]
    info = []
    for _ in pairs:
        Q = rng.normal(size=(3, 3))
        info.append(Q @ Q.T + np.eye(3))
    loop = [k >= 5 for k in range(len(pairs))]
    g = PoseGraph(list(X), [p[0] for p in pairs], [p[1] for p in pairs],
                  [rng.normal(0, 1, 3) for _ in pairs], info, loop)
    scale = 2.0
    H, grad, chi2 = g.normal_equations(X, scale)
    e0 = g.residuals(X)
    H_ref, g_ref, chi2_ref = np.zeros((3 * n, 3 * n)), np.zeros(3 * n), 0.0
    for k in range(len(pairs)):
        J = np.zeros((3, 3 * n))
        for v in range(3 * n):
            dX = X.copy()
            dX.flat[v] += 1e-6
            d = g.residuals(dX)[k] - e0[k]
            d[2] = wrap(d[2])
            J[:, v] = d / 1e-6
        m2 = e0[k] @ info[k] @ e0[k]
        w = 1.0 / (1.0 + m2 / scale ** 2) if loop[k] else 1.0
        H_ref += w * J.T @ info[k] @ J
        g_ref += w * J.T @ info[k] @ e0[k]
        chi2_ref += w * m2
    assert np.allclose(H.toarray(), H_ref, atol=1e-4 * np.abs(H_ref).max())
    assert np.allclose(grad, g_ref, atol=1e-4 * np.abs(g_ref).max())
    assert chi2 == pytest.approx(chi2_ref)
    assert np.allclose(H.toarray(), H.toarray().T)
    # taken a few edges at a time (a long run's graph), the same equations
    Hc, gc, chi2c = g.normal_equations(X, scale, chunk=3)
    assert np.allclose(Hc.toarray(), H.toarray(), rtol=1e-12, atol=1e-9)
    assert np.allclose(gc, grad, rtol=1e-12, atol=1e-9) and chi2c == pytest.approx(chi2)


@pytest.mark.parametrize("cg_iterations", [400, 1])
def test_large_normal_equations_go_to_conjugate_gradients(monkeypatch, cg_iterations):
    """Above DIRECT_MAX the step comes from block-Jacobi CG (or, when CG does not converge,
    from the factor): the same solution either way."""
    import cgamap.mapping.posegraph as pg

    g, true = _square_loop_graph(seed=3)
    exact = PoseGraph([p.copy() for p in g.poses], g.ei, g.ej, g.z, g.info, g.loop)
    exact.optimize()
    calls = []
    monkeypatch.setattr(pg, "DIRECT_MAX", 0)
    monkeypatch.setattr(pg, "CG_ITERATIONS", cg_iterations)
    real_pcg = pg._pcg
    monkeypatch.setattr(pg, "_pcg", lambda *a: calls.append(1) or real_pcg(*a))
    g.optimize()
    assert calls
    assert np.allclose(np.array(g.poses), np.array(exact.poses), atol=1e-6)
    assert ate(np.array(g.poses), true)["ate_trans_m"] < 0.1


def test_block_jacobi_inverts_pose_and_line_blocks():
    """The preconditioner is the exact inverse of a block-diagonal matrix of 3x3 pose
    blocks followed by 2x2 line blocks (phi, rho): a line far from the origin couples its
    two unknowns strongly, and inverting only their diagonal left CG unconverged."""
    import cgamap.mapping.posegraph as pg
    import scipy.sparse as sp

    rng = np.random.default_rng(2)
    poses, lines = 5, 4
    blocks = []
    for size in [3] * poses + [2] * lines:
        G = rng.normal(size=(size, size))
        blocks.append(G @ G.T + 0.1 * np.eye(size))
    # a wall 30 m out: rho follows phi by 30 m per radian
    blocks[poses] = np.array([[900.0, 30.0], [30.0, 1.0]]) + 1e-3 * np.eye(2)
    A = sp.block_diag(blocks, format="csr")
    v = rng.normal(size=A.shape[0])
    assert np.allclose(pg._block_jacobi(A, poses)(A @ v), v, rtol=1e-9, atol=1e-9)


def test_line_adjustment_by_conjugate_gradients_matches_the_factor(monkeypatch):
    """Above DIRECT_MAX the line adjustment's steps come from CG, without falling back to
    the factor, and give the factor's poses."""
    import cgamap.mapping.posegraph as pg
    from cgamap.mapping.line_adjust import adjust, observations
    from test_mapping_adjust import _mapped, _truth, _weak_chain

    truth = _truth(40)
    obs = observations(_mapped(truth).map)
    rng = np.random.default_rng(3)
    X0 = truth + np.column_stack([rng.normal(0, 0.04, (len(truth), 2)),
                                  rng.normal(0, np.deg2rad(1.0), len(truth))])
    X0[0] = truth[0]
    exact, _ = adjust(X0, _weak_chain(X0), obs, 0)
    monkeypatch.setattr(pg, "DIRECT_MAX", 0)
    monkeypatch.setattr(pg, "spsolve", lambda *a, **k: pytest.fail("fell back to the factor"))
    X, info = adjust(X0, _weak_chain(X0), obs, 0)
    assert info["iterations"] >= 2
    assert np.allclose(X, exact, atol=1e-7)


def test_neighbour_pairs_are_the_same_in_any_chunking():
    from cgamap.mapping.finishing import NeighbourParams, neighbour_pairs

    rng = np.random.default_rng(4)
    X = np.column_stack([rng.uniform(0, 6, 500), rng.uniform(0, 3, 500), np.zeros(500)])
    scans = [(np.zeros((3, 2)), np.ones((3, 2)))] * len(X)
    NP = NeighbourParams(max_pairs=8)
    whole = neighbour_pairs(X, scans, NP, chunk=len(X))
    assert len(whole) > 8 * 300  # the cap is in play
    assert np.array_equal(neighbour_pairs(X, scans, NP, chunk=37), whole)
    per_node = np.bincount(whole[:, 1], minlength=len(X))
    assert per_node.max() <= 8 + NP.previous


def _stub_pair(extrapolation: float):
    """Scan i sees two 4 m walls and the end wall; scan j (same pose) sees the upper wall
    and the end wall whole but the lower one only as a 0.4 m stub, tilted 0.6 deg by
    noise."""
    from cgamap.mapping.correction import CorrectionParams, correct_batch
    from cgamap.mapping.matching import LineIndex

    src_a = np.array([[[0.0, -1.0], [4.0, 1.0], [4.0, -1.0]]])
    src_b = np.array([[[4.0, -1.0], [0.0, 1.0], [4.0, 1.0]]])
    tilt = np.deg2rad(0.6)
    stub = 0.4 * np.array([np.cos(tilt), np.sin(tilt)])
    dst_a = np.array([[[0.0, -1.0], [4.0, 1.0], [4.0, -1.0]]])
    dst_b = np.array([[[0.0, -1.0] + stub, [0.0, 1.0], [4.0, 1.0]]])
    P = CorrectionParams(gates=(0.3, 0.15, 0.08), angle_gates_deg=(6.0, 4.0, 3.0),
                         extrapolation=extrapolation)
    res = correct_batch(src_a, src_b, LineIndex.of(dst_a, dst_b), np.zeros((1, 3)), 0.5, P)
    assert (res.matches[0] >= 0).all()
    return np.rad2deg(res.pose[0, 2])


def test_a_stub_extrapolated_over_metres_does_not_tilt_the_match():
    # the stub's error, carried 4 m along the long wall, weighs as much as the whole upper
    # wall unless points past the stub's end count with its direction's uncertainty
    assert abs(_stub_pair(0.0)) > 0.1
    assert abs(_stub_pair(0.1)) < 0.03


def test_a_short_cross_piece_weighs_as_a_longer_one_along_a_corridor():
    # a corridor that narrows by 0.2 m at x = 2: that step is all that fixes x
    w = world([(-10, -1, 10, -1), (-10, 1, 2, 1), (2, 1, 2, 0.8), (2, 0.8, 10, 0.8)])
    seg = segments_from_scan(scan(w, (0.0, 0.0, 0.0), n=360))
    L = seg.length
    step_piece = np.abs(seg.b[:, 1] - seg.a[:, 1]) > 0.5 * L  # the cross piece(s)
    assert step_piece.any() and L[step_piece].max() < 0.25
    idx = LineIndex.of(seg.a[None], seg.b[None])

    def solve(min_length, x0):
        return correct_batch(seg.a[None], seg.b[None], idx, np.array([[x0, 0.0, 0.0]]), 1.0,
                             CorrectionParams(min_length=min_length))

    # at the true pose: along the corridor the piece now counts as a 0.5 m one, across it
    # and in the residual nothing changes
    plain, short = solve(0.0, 0.0), solve(0.5, 0.0)
    ratio = short.info_data[0, 0, 0] / plain.info_data[0, 0, 0]
    assert ratio == pytest.approx((0.5 * step_piece.sum()) / L[step_piece].sum(), rel=0.05)
    assert short.info_data[0, 1, 1] == pytest.approx(plain.info_data[0, 1, 1], rel=0.02)
    assert short.rms[0] == pytest.approx(plain.rms[0], abs=1e-9)
    # from 8 cm off along the corridor it pulls the pose back against the prior harder
    plain, short = solve(0.0, 0.08), solve(0.5, 0.08)
    assert abs(short.pose[0, 0]) < abs(plain.pose[0, 0]) - 0.01


@pytest.mark.parametrize("heading", [0.0, 0.7])
def test_prediction_share_follows_what_the_walls_leave_open(heading):
    # a corridor along the robot's heading: a change in the prediction along it stays in
    # the pose (share 1), across it the walls hold (share ~0); the share is in the frame of
    # the pose predicted from, so turning the whole scene does not change it
    from cgamap.mapping.slam2d import prediction_shares

    c_, s_ = np.cos(heading), np.sin(heading)
    walls = [(-10, -1, 10, -1), (-10, 1, 10, 1)]
    turned = np.array([(c_ * x0 - s_ * y0, s_ * x0 + c_ * y0, c_ * x1 - s_ * y1,
                        s_ * x1 + c_ * y1) for x0, y0, x1, y1 in walls])
    seg = segments_from_scan(scan(world(turned), (0.0, 0.0, heading)))
    P = CorrectionParams()
    moved = []
    for shift in (np.zeros(2), np.array([0.05, 0.05])):
        pred = np.array([*(np.array([[c_, -s_], [s_, c_]]) @ (np.array([0.3, 0.02]) + shift)),
                         heading])
        c = correct_pose(seg, turned[:, :2], turned[:, 2:], pred, step=1.0, params=P)
        moved.append(c.pose)
    share = prediction_shares(c.cov[None], P, np.array([1.0]), np.array([heading]))[0]
    assert share[0, 0] == pytest.approx(1.0, abs=0.02)
    assert abs(share[1, 1]) < 0.2  # the correction's information is modest by design
    # what the pose did when the prediction moved 5 cm along and across: the share's answer
    body = np.array([[c_, s_], [-s_, c_]]) @ (moved[1][:2] - moved[0][:2])
    assert body == pytest.approx(share[:2, :2] @ [0.05, 0.05], abs=0.005)
