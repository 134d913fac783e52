"""The 2D mapper's finishing pass: every revisit matched scan to scan, round after round.

A snapshot of the mapper's graph, scans and walls (:class:`FinishJob`, taken by
:meth:`.slam2d.Mapper.finishing_job`) gets the tracking sweep (:func:`sweep_matches`: a
closure by point-to-line tracking for every scan near an earlier one), then ``rounds`` of
:func:`neighbour_matches` (every pair of scans within reach, matched with the current
estimate as the prior and each pair's turn from its walls, :func:`pair_turns`), each followed
by a graph solve, and the line adjustment; :meth:`FinishJob.run` works on the snapshot only,
so the daemon runs it in another thread.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from .correction import CorrectionParams, correct_batch
from .evaluation import ate
from .jit import kernel
from .line_adjust import AdjustParams, Contributions, adjust, associate
from .matching import LineIndex
from .odometry import move_points, relative, step_calibration
from .odometry import wrap_angle as wrap
from .posegraph import EdgeArrays, PoseGraph

if TYPE_CHECKING:
    from .slam2d import LoopParams


def pad_segments(segs: list[tuple[np.ndarray, np.ndarray]],
                 fill: float) -> tuple[np.ndarray, np.ndarray]:
    """Segment sets of different sizes as (P, k, 2) arrays a, b, padded with ``fill``."""
    k = max(len(a) for a, _ in segs)
    A = np.full((len(segs), k, 2), fill)
    B = np.full((len(segs), k, 2), fill)
    for r, (a, b) in enumerate(segs):
        A[r, :len(a)], B[r, :len(b)] = a, b
    return A, B


@dataclass(frozen=True)
class NeighbourParams:
    """The finishing pass: every scan matched against each scan near it (scan-to-scan, no
    fused map in between), each good match an edge of the pose graph.  Scan-to-map steps
    inherit the fused map's bias (walls fused from slightly wrong poses, chords of curved
    walls); direct pairs do not, and a scan's many neighbours average out its errors."""

    enabled: bool = True
    radius: float = 2.5           # pairs of scans whose positions are this close (m) ...
    previous: int = 3             # ... and each scan with this many before it
    max_std: float = 0.1          # accept: translation std in the best-known direction (m)
    # ... and this share of the scan's segment length matched.  Low on purpose: a pair that
    # shares one wall through a doorway is what ties a room to its corridor (the edge keeps
    # only the matches' own information, and a robust kernel); 0.3 -> 0.1 measured 0.077 ->
    # 0.075 m mean ATE over 12 noise seeds on the Intel log
    min_matched: float = 0.1
    floor: tuple[float, float] = (0.01, 0.0033)  # added to each edge's std (m, rad)
    sequential_weight: float = 0.3   # the scan-to-map steps' edges then count this much
    # ... and the online loop closures this much: each was solved against a few scans'
    # fused segments and given a fixed std (5 cm, 0.6 deg), where the pass's edges carry
    # each scan pair's own information.  On Intel (high noise, seeds 0-7) 1 -> 0.01 took
    # the mean ATE from 0.068 to 0.061 m and the relations' from 0.0365 to 0.0359 m (0.2:
    # no change; 0.05 and 0.02 about half the gain); the 150 m corridor, where the pass's
    # pairs are weak along the corridor, went from 0.117 to 0.134 m
    closure_weight: float = 0.01
    rounds: int = 2               # match again from the re-optimised poses (2: measured best)
    # ... and on, up to ``max_rounds``, while a round still moved the map by ``converged`` (m,
    # RMS over the nodes after a rigid alignment, which no anchor choice changes) or more
    # (``map build`` reports each round's move: ``neighbour_round_moves_m``).  Off by default:
    # MIT CSAIL (a scan a metre), high noise, seeds 0-3, whose second round still moves the
    # map 5-9 cm: mean ATE 0.106 -> 0.097 m with 4 rounds at most (0.097 with 3); Intel's
    # second round moves it 1.2-2.1 cm (seeds 0-15 unchanged; a third round forced: seeds 0-7
    # 0.0567 -> 0.0575 m); but Killian Court, whose rounds do not settle (0.13, 0.08, 0.11
    # m), high seeds 0 / 1: 0.54 / 0.60 -> 0.67 / 0.63 m with 4 (0.62 / 0.60 with 3), and
    # its pass took twice as long
    max_rounds: int = 2
    converged: float = 0.03
    coarse_first: bool = True     # the first round farther and with a wider first gate
    prior_step: float = 0.5       # the current estimate as prior, as wide as after this step
    chunk: int = 512              # pairs solved together (memory ~ chunk * segments^2)
    # each scan's spatial partners among the earlier scans, at most this many, spread evenly
    # over time (0: all): a dense log or a robot that keeps to one room must not make the
    # pairs quadratic, and the spread keeps the oldest visits as well as the last pass.
    # 32 leaves the Intel log's pass as it was within noise (mean ATE +0.7 mm over 4 seeds)
    # and cuts a 1960-scan loop run at 5 cm spacing from 108 s to 41 s
    max_pairs: int = 32
    # wide first gates: a region the online closures left bent by decimetres is pulled in.
    # Extrapolated stubs down-weighted (CorrectionParams.extrapolation): pairs of scans taken
    # in opposite directions match one scan's wall to a stub of it in the other; on a 150 m
    # corridor (noise-free odometry, no loop closing) 0.23 -> 0.04 m ATE; on Intel, seeds
    # 0-11: the relations 0.041 -> 0.038 m mean, the ATE against the reference 0.074 ->
    # 0.073 m mean (seed 0: 0.067 -> 0.069 m)
    # A short cross piece (a door jamb, a recess's side) fixes its line's offset as well as a
    # 0.5 m one (CorrectionParams.min_length): along a corridor it is all that fixes a pair,
    # and the odometry's length noise is what the Intel runs lose most to.  Intel seeds
    # 0-3, mean ATE: 0.0556 -> 0.0545 m (0.3 m: 0.0553, 1 m: 0.0556; in the scan-to-map
    # correction too: 0.0582)
    correction: CorrectionParams = field(default_factory=lambda: CorrectionParams(
        gates=(0.6, 0.4, 0.25, 0.15, 0.1, 0.06),
        angle_gates_deg=(15.0, 10.0, 7.0, 5.0, 3.0, 2.5), extrapolation=0.1,
        min_length=0.5))
    # the odometry calibration re-estimated from each round's consecutive scan pairs
    # (:func:`.odometry.step_calibration`), and the scan-to-map steps re-predicted with it
    # (:func:`_recalibrate`): along a corridor a step is the odometry's, and the online
    # estimate wanders by about 1 % in scale and 0.25 deg/m in drift
    recalibrate: bool = True
    # a pair whose walls' directions, at the current estimate, disagree by more than
    # ``turn_min`` (rad; looked for within ``turn_reach``, 0: off) is solved again from the
    # turn that lines them up (:func:`pair_turns`: seed eq. 10 in the Hough domain), and the
    # answer that matches clearly more of the scan (or as much with a smaller residual)
    # kept.  The correction's own reach in rotation is a few degrees: a step the mapper
    # took 4-8 deg wrong (a sparse log's turn, a slip recovery's choice) was kept by the
    # pass, or turned into an edge as wrong.  Intel, high noise: every 2nd scan (a scan a
    # metre), seeds 0-7, mean ATE 0.103 -> 0.088 m (every seed better); every 3rd 0.56 ->
    # 0.46 m; the whole log, seeds 0-15, 0.0582 -> 0.0583 m (1.5 deg: 0.0574 m over seeds
    # 0-7, not 0.0567); Killian, high, seed 0: 0.58 -> 0.54 m
    turn_reach: float = np.deg2rad(10.0)
    turn_min: float = np.deg2rad(3.0)


def _spread_pairs(tree: cKDTree, X: np.ndarray, later: np.ndarray,
                  NP: NeighbourParams) -> np.ndarray:
    """(p, 2) pairs (j, i), j < i, for the nodes i of ``later``: the earlier nodes within
    ``radius``, at most ``max_pairs`` of them per i, evenly spread over their order."""
    found = tree.query_ball_point(X[later, :2], NP.radius)
    counts = np.array([len(f) for f in found], int)
    if not counts.sum():
        return np.zeros((0, 2), int)
    i = np.repeat(later, counts)
    j = np.concatenate([np.asarray(f, int) for f in found])
    near = np.column_stack([j, i])[j < i]
    near = near[np.lexsort((near[:, 0], near[:, 1]))]       # by later node, then earlier
    K = NP.max_pairs
    if K > 0 and len(near):
        _, first, count = np.unique(near[:, 1], return_index=True, return_counts=True)
        c = np.repeat(count, count)
        rank = np.arange(len(near)) - np.repeat(first, count)
        # the picks are ranks round(k * s), k = 0..K-1, s = (c-1)/(K-1) > 1: a rank is one
        # when the nearest pick index maps back onto it
        s = np.maximum(c - 1, 1) / max(K - 1, 1)
        keep = (c <= K) | (np.round(np.round(rank / s) * s) == rank)
        near = near[keep]
    return near


def neighbour_pairs(X: np.ndarray, scans: list, NP: NeighbourParams,
                    chunk: int = 250) -> np.ndarray:
    """(p, 2) node pairs j < i for the neighbour pass: positions ``X`` within ``radius``
    (for each later node at most ``max_pairs`` of them, evenly spread over the earlier
    nodes' order), and each node with its ``previous`` predecessors; nodes with fewer than
    two segments left out."""
    n = len(X)
    # by chunks of later nodes: a robot that has driven the same rooms for hours has
    # thousands of earlier scans near each one, and all the pairs at once would not fit
    # (245 laps of the simulated loop, first round: peak 690 MB by 2 000 nodes, 97 MB by
    # 250, and faster); each chunk searches only the nodes up to its own (pairs look back)
    near = [_spread_pairs(cKDTree(X[:c1, :2]), X, np.arange(c0, c1), NP)
            for c0, c1 in ((c, min(c + chunk, n)) for c in range(0, n, chunk))
            ] or [np.zeros((0, 2), int)]
    near = np.concatenate(near)
    i = np.arange(n)
    seq = [np.column_stack([i[k:] - k, i[k:]]) for k in range(1, NP.previous + 1)]
    pairs = np.unique(np.concatenate([near, *seq]).astype(int), axis=0)
    counts = np.array([len(a) for a, _ in scans])
    keep = (counts[pairs[:, 0]] >= 2) & (counts[pairs[:, 1]] >= 2)
    return pairs[keep]


def round_params(NP: NeighbourParams, r: int) -> NeighbourParams:
    """Round ``r``'s parameters: with ``coarse_first`` the first round reaches 1.6x farther
    with a wider first gate, so a stretch the online closures left off by more than the fine
    gates reach comes in."""
    if r > 0 or not NP.coarse_first:
        return NP
    return replace(NP, radius=NP.radius * 1.6, correction=replace(
        NP.correction, gates=(1.0, *NP.correction.gates),
        angle_gates_deg=(20.0, *NP.correction.angle_gates_deg)))


def neighbour_matches(X: np.ndarray, scans: list, NP: NeighbourParams,
                      pairs: np.ndarray | None = None,
                      stop=None) -> EdgeArrays:
    """The finishing pass's matching (:class:`NeighbourParams`): scan i's segments against
    scan j's for every neighbour pair (solved in batches, :func:`.correction.correct_batch`);
    the good matches as edges (:class:`.posegraph.EdgeArrays`, i the earlier scan of each
    pair) carrying the matches' own information.
    ``pairs`` defaults to :func:`neighbour_pairs`; ``stop()`` true between batches abandons
    the pass (returns [])."""
    pairs = neighbour_pairs(X, scans, NP) if pairs is None else pairs
    f_t, f_r = NP.floor
    floor = np.diag([f_t ** 2, f_t ** 2, f_r ** 2])
    # batches of like-sized scans: each batch is padded to its largest pair, so a pair of
    # small scans next to a cluttered one would otherwise cost as much as the clutter
    counts = np.array([len(a) for a, _ in scans])
    order = np.lexsort((counts[pairs[:, 0]], counts[pairs[:, 1]])) if len(pairs) else []
    found = []
    for c0 in range(0, len(pairs), NP.chunk):
        if stop is not None and stop():
            return EdgeArrays.empty()
        j, i = pairs[order[c0:c0 + NP.chunk]].T
        src_a, src_b = pad_segments([scans[k] for k in i], 0.0)
        dst_a, dst_b = pad_segments([scans[k] for k in j], 1e6)  # padding never matches
        pred = relative(X[j], X[i])
        index = LineIndex.of(dst_a, dst_b)
        res = correct_batch(src_a, src_b, index, pred, NP.prior_step, NP.correction)
        if NP.turn_reach > 0:
            _turned(res, src_a, src_b, index, pred, NP)
        # the matches' own information (the prior taken out): along a corridor the pair
        # says nothing, and its edge must not pin the current estimate there.
        # (H^-1 + F)^-1 written as H (I + F H)^-1, which holds for a singular H too
        info = res.info_data @ np.linalg.inv(np.eye(3) + floor @ res.info_data)
        info = 0.5 * (info + np.swapaxes(info, 1, 2))
        best = np.linalg.eigvalsh(info[:, :2, :2])[:, -1]  # the best-known direction
        ok = (best >= NP.max_std ** -2) & (res.matched_fraction >= NP.min_matched)
        found.append(EdgeArrays.of(j[ok], i[ok], res.pose[ok], info[ok]))
    # arrays, not an object per edge: a 12 000-scan pass finds 400 000 edges.  In the
    # graph's edge order, the pairs' order (by later node, then earlier)
    E = EdgeArrays.concat(found)
    return E.select(np.lexsort((E.i, E.j)))


def _turned(res, src_a: np.ndarray, src_b: np.ndarray, index: LineIndex, pred: np.ndarray,
            NP: NeighbourParams) -> None:
    """:attr:`NeighbourParams.turn_reach`: the pairs of ``res`` (solved from ``pred``) whose
    walls' directions call for a turn of ``turn_min`` or more, solved again from that turn;
    ``res`` takes the new answer where it matches over 5 % more of the scan, or as much
    (2 % less at most) with a smaller residual."""
    turn = pair_turns(src_a, src_b, index.a, index.b, pred[:, 2], NP.turn_reach)
    alt = np.nonzero(np.abs(turn) >= NP.turn_min)[0]
    if not len(alt):
        return
    start = pred[alt].copy()
    start[:, 2] = wrap(start[:, 2] + turn[alt])
    got = correct_batch(src_a[alt], src_b[alt], index.subset(alt), start, NP.prior_step,
                        NP.correction)
    was_m, was_r = res.matched_fraction[alt], res.rms[alt]
    better = (got.matched_fraction > was_m + 0.05) | (
        (got.matched_fraction >= was_m - 0.02) & (got.rms < was_r))
    take = alt[better]
    for name in ("pose", "cov", "matched_fraction", "rms", "matches", "info_data"):
        getattr(res, name)[take] = getattr(got, name)[better]


def pair_turns(src_a: np.ndarray, src_b: np.ndarray, dst_a: np.ndarray, dst_b: np.ndarray,
               theta: np.ndarray, reach: float, bin_rad: float = np.deg2rad(0.5)
               ) -> np.ndarray:
    """Per pair, the turn (rad) within ``reach`` that lays the source segments' directions
    (turned by ``theta``) onto the destination's: eq. 10's theta_err read in the Hough
    domain, as :func:`.relocalize.rotation_peaks` reads eq. 9 for one scan against a map
    (the same length-weighted histogram of undirected direction differences), here for a
    batch of pairs and only its one peak within ``reach`` (summed over three neighbouring
    bins, refined to the weighted mean of those bins).  Compiled: the finishing pass asks
    it for every scan pair.  0 where no two directions come within ``reach``.  Segments
    (P, k, 2) and (P, m, 2), padded with zero-length segments (they weigh nothing)."""
    f = np.ascontiguousarray
    return _pair_turns(f(src_a, dtype=float), f(src_b, dtype=float), f(dst_a, dtype=float),
                       f(dst_b, dtype=float), f(theta, dtype=float), float(reach),
                       float(bin_rad))


@kernel
def _pair_turns(sa, sb, da, db, theta, reach, bin_rad):
    P, k, m = sa.shape[0], sa.shape[1], da.shape[1]
    half = int(np.ceil(reach / bin_rad))
    nb = 2 * half + 1
    out = np.zeros(P)
    hist = np.zeros(nb)
    wsum = np.zeros(nb)
    ang_d = np.zeros(m)
    len_d = np.zeros(m)
    for p in range(P):
        for j in range(m):
            dx, dy = db[p, j, 0] - da[p, j, 0], db[p, j, 1] - da[p, j, 1]
            ang_d[j] = np.arctan2(dy, dx)
            len_d[j] = np.sqrt(dx * dx + dy * dy)
        hist[:] = 0.0
        wsum[:] = 0.0
        for i in range(k):
            dx, dy = sb[p, i, 0] - sa[p, i, 0], sb[p, i, 1] - sa[p, i, 1]
            ls = np.sqrt(dx * dx + dy * dy)
            if ls <= 0.0:
                continue
            a = np.arctan2(dy, dx) + theta[p]
            for j in range(m):
                w = min(ls, len_d[j])
                if w <= 0.0:
                    continue
                d = (ang_d[j] - a + 0.5 * np.pi) % np.pi - 0.5 * np.pi  # undirected
                if abs(d) > reach:
                    continue
                q = min(max(int(np.floor(d / bin_rad + 0.5)) + half, 0), nb - 1)
                hist[q] += w
                wsum[q] += w * d
        best, at = 0.0, -1
        for q in range(nb):
            v = hist[q] + (hist[q - 1] if q > 0 else 0.0) + (hist[q + 1] if q < nb - 1 else 0.0)
            if v > best:
                best, at = v, q
        if at < 0:
            continue
        lo, hi = max(at - 1, 0), min(at + 1, nb - 1)
        tot = 0.0
        acc = 0.0
        for q in range(lo, hi + 1):
            tot += hist[q]
            acc += wsum[q]
        out[p] = acc / tot if tot > 0.0 else 0.0
    return out


def replace_neighbour_edges(g: PoseGraph, block: tuple[int, int], weighted: int,
                            edges: EdgeArrays, NP: NeighbourParams
                            ) -> tuple[tuple[int, int], int]:
    """Put a neighbour pass's edges (robust) in ``g`` in place of the previous pass's (the
    edges ``block``); the scan-to-map steps' edges and the online closures from ``weighted``
    on are down-weighted to ``sequential_weight`` and ``closure_weight`` (the earlier ones
    already are).  Returns the new block and mark."""
    n0, n1 = block
    if n1 > n0:
        for name in ("ei", "ej", "z", "info", "loop"):
            del getattr(g, name)[n0:n1]
        weighted -= n1 - n0 if weighted >= n1 else 0
    seq = weighted + np.nonzero(~g.loop[weighted:])[0]
    g.info[seq] = g.info[seq] * NP.sequential_weight
    closures = weighted + np.nonzero(g.loop[weighted:])[0]
    g.info[closures] = g.info[closures] * NP.closure_weight
    n0 = len(g.ei)
    g.add_edges(EdgeArrays.of(edges.i, edges.j, edges.z, edges.info, True))
    return (n0, len(g.ei)), len(g.ei)


@dataclass
class FinishJob:
    """The finishing pass (the tracking sweep, ``rounds`` of :func:`neighbour_matches`, each
    followed by a graph solve, more until one moves the map less than ``converged``, then the
    line adjustment) on a snapshot of a mapper's graph,
    scans and walls; :meth:`run` works on the snapshot only, so it may run in another
    thread."""

    params: NeighbourParams
    graph: PoseGraph
    scans: list
    anchors: list
    base: int                      # the mapper's ``dropped`` at the snapshot
    block: tuple[int, int]
    weighted: int
    sweep: LoopParams | None = None            # tracking closures first (None: not)
    travel: np.ndarray | None = None           # odometry distance per node, for the sweep
    # the sweep's and the last round's edges (i the earlier node of each)
    edges: EdgeArrays = field(default_factory=lambda: EdgeArrays.empty())
    poses: np.ndarray | None = None            # the snapshot's nodes, re-optimised
    pairs: int = 0                             # scan pairs matched, all rounds
    round_moves: list = field(default_factory=list)  # how far each round moved the map (m)
    sweep_edges: int = 0
    source: object = field(default=None, repr=False)  # the mapper it was taken from
    lines: Contributions | None = None         # the map's scan segments, for ...
    adjust: AdjustParams | None = None         # ... the line adjustment (None: not)
    adjusted: dict = field(default_factory=dict)  # its figures
    steps: np.ndarray | None = None  # per node: raw odometry step and its calibration (5,)
    shares: np.ndarray | None = None  # ... and the share of the prediction it kept (3, 3)
    calibration: dict = field(default_factory=dict)  # the re-estimated one, when found

    @property
    def nodes(self) -> int:
        return len(self.graph.poses)

    def run(self, stop=None) -> FinishJob:
        """Compute the edges and poses; ``stop()`` true abandons (edges stay empty)."""
        NP = self.params
        g = self.graph
        if self.nodes < 2:
            return self
        swept = EdgeArrays.empty()
        if self.sweep is not None:
            # before the rounds: each revisit tied to its earlier visit's submap; the
            # edges stay in the block with every round's
            swept = sweep_matches(np.array(g.poses), self.scans, self.travel, self.sweep, stop)
            self.sweep_edges = len(swept)
            if len(swept):
                self.block, self.weighted = replace_neighbour_edges(
                    g, self.block, self.weighted, swept, NP)
                g.optimize(fixed=self.anchors)
                self.edges = swept
        moved = np.inf  # how far the last round moved the map (m)
        for r in range(max(NP.rounds, NP.max_rounds) if NP.rounds else 0):
            if r >= NP.rounds and moved < NP.converged:
                break
            rp = round_params(NP, r)
            X = np.array(g.poses)
            pairs = neighbour_pairs(X, self.scans, rp)
            self.pairs += len(pairs)
            got = neighbour_matches(X, self.scans, rp, pairs, stop)
            if stop is not None and stop():
                self.edges, self.poses = EdgeArrays.empty(), None
                return self
            if not len(got):
                moved = 0.0  # nothing matched, nothing moved: no further round
                continue
            both = EdgeArrays.concat([swept, got])
            self.block, self.weighted = replace_neighbour_edges(
                g, self.block, self.weighted, both, NP)
            if NP.recalibrate and self.steps is not None:
                self._recalibrate(got)
            g.optimize(fixed=self.anchors)
            self.edges = both
            moved = ate(np.array(g.poses), X)["ate_trans_m"]
            self.round_moves.append(round(moved, 4))
        if self.lines is not None and self.adjust is not None:
            X0 = np.array(g.poses)
            X, self.adjusted = adjust(X0, g, associate(self.lines, X0, self.adjust),
                                      self.anchors, self.adjust)
            g.poses = X
        self.poses = np.array(g.poses)
        return self


    def _recalibrate(self, got: EdgeArrays) -> None:
        """Re-estimate the odometry calibration from ``got``'s pairs of consecutive scans
        and re-predict the graph's scan-to-map steps with it: each step's measurement moves
        by what the new calibration changes in its prediction, times the share of the
        prediction its pose kept (along a corridor all of it, where walls fixed it none).
        Intel, high noise, mean ATE over seeds 0-15: 0.0585 -> 0.0576 m (with the whole
        change applied to every step 0.0571 m; with the preset's true calibration so
        applied, seeds 0-7: 0.0563 -> 0.0536 m)."""
        g, st = self.graph, self.steps
        nxt = np.nonzero(got.j == got.i + 1)[0]
        est = step_calibration(got.z[nxt], got.info[nxt], st[got.j[nxt], :3])
        if est is None:
            return
        scale, drift, used = est
        ei, ej, loop = g.ei.array(), g.ej.array(), g.loop.array()
        e = np.nonzero(~loop & (ej == ei + 1))[0]  # scan-to-map steps (passes' edges: loop)
        k = ej[e]
        d = np.hypot(st[k, 0], st[k, 1])
        moved = np.column_stack([(scale - st[k, 3]) * st[k, 0], (scale - st[k, 3]) * st[k, 1],
                                 -(drift - st[k, 4]) * d])
        z = g.z.array()
        z[e] += np.einsum("kab,kb->ka", self.shares[k], moved)
        st[k, 3], st[k, 4] = scale, drift  # what they are predicted with now
        self.calibration = {"scale": scale, "drift_per_m": drift, "steps": used}


def calibration_figures(cal: dict) -> dict:
    """A finishing pass's odometry calibration for reports: ``scale`` (true / odometry
    distance), ``drift_deg_per_m`` (heading the odometry gains per metre), ``steps`` used."""
    return {"scale": round(float(cal["scale"]), 5),
            "drift_deg_per_m": round(float(np.degrees(cal["drift_per_m"])), 4),
            "steps": int(cal["steps"])}


def sweep_matches(X: np.ndarray, scans: list, travel: np.ndarray, LP: LoopParams,
                  stop=None) -> EdgeArrays:
    """Tracking closures (as :meth:`.slam2d.Mapper._closure_by_tracking` finds them online)
    from kept scans instead of the map's contributions, all candidates solved together: every
    ``sweep_every``-th scan against the submap (scans +- ``window``) of its nearest earlier
    visit within ``sweep_radius``; a tracking closure that fixes the pose in every direction
    and fits becomes an edge (j to i, robust)."""
    n = len(X)
    i = np.arange(0, n, LP.sweep_every)
    last = np.minimum(np.searchsorted(travel, travel[i] - LP.min_travel, side="right") - 1,
                      i - LP.min_separation)
    counts = np.array([len(a) for a, _ in scans])
    i, last = i[(last >= 0) & (counts[i] >= 2)], last[(last >= 0) & (counts[i] >= 2)]
    none = EdgeArrays.empty()
    if not len(i):
        return none
    # the nearest earlier visit: among each scan's nearest few, the first old enough
    k = min(n, 64)
    d, nb = cKDTree(X[:, :2]).query(X[i, :2], k=k, distance_upper_bound=LP.sweep_radius)
    d, nb = d.reshape(len(i), k), nb.reshape(len(i), k)
    ok = np.isfinite(d) & (nb <= last[:, None])
    has = ok.any(axis=1)
    i, last = i[has], last[has]
    j = nb[has, np.argmax(ok[has], axis=1)]
    st, sr = LP.sigma
    info = np.diag([st ** -2, st ** -2, sr ** -2])
    found = []
    chunk = 128  # the submaps are ~window * 2 + 1 scans: more segments per problem
    for c0 in range(0, len(i), chunk):
        if stop is not None and stop():
            return none
        ii, jj, ll = i[c0:c0 + chunk], j[c0:c0 + chunk], last[c0:c0 + chunk]
        subs, keep = [], []
        for a, (jk, lk) in enumerate(zip(jj, ll, strict=True)):  # per scan pair, not per point
            ks = list(range(max(jk - LP.window, 0), min(jk + LP.window, lk) + 1))
            rel = relative(X[jk], X[ks])
            parts = [(move_points(scans[m][0], r), move_points(scans[m][1], r))
                     for m, r in zip(ks, rel, strict=True)]
            sa = np.concatenate([p[0] for p in parts])
            if len(sa) < 3:
                continue
            subs.append((sa, np.concatenate([p[1] for p in parts])))
            keep.append(a)
        if not keep:
            continue
        ii, jj = ii[keep], jj[keep]
        src_a, src_b = pad_segments([scans[m] for m in ii], 0.0)
        dst_a, dst_b = pad_segments(subs, 1e6)
        res = correct_batch(src_a, src_b, LineIndex.of(dst_a, dst_b), relative(X[jj], X[ii]),
                            4.0, LP.tracking)
        std = np.sqrt(np.linalg.eigvalsh(res.cov[:, :2, :2])[:, -1])
        good = (std <= LP.max_std) & (res.matched_fraction >= max(0.5, LP.tracking_score)) & (
            res.rms <= 0.05)
        found.append(EdgeArrays.of(jj[good], ii[good], res.pose[good],
                                   np.broadcast_to(info, (int(good.sum()), 3, 3))))
    return EdgeArrays.concat(found)
