"""The 2D line mapper: scan -> segments -> laser chain to global -> match against the whole
global map -> pose correction (eqs. 10-11) -> merge, with loop closure on a pose graph.

Per scan (:meth:`Mapper.step`):
1. split-and-merge segments in the laser frame (:mod:`.segments`);
2. prediction: the last pose composed with the odometry increment, corrected by the learnt
   odometry heading drift and scale;
3. correction against the whole global map (sphere test eq. 15 + line gates, robust
   point-to-line least squares with the odometry as prior; :mod:`.correction`);
4. a pose-graph node with a sequential edge; every few scans, a loop closure against an
   earlier visit's segments -- point-to-line tracking first, Hough-domain relocalisation
   (§V) when the drift is larger -- and, when a closure disagrees, a graph solve that moves
   the map with it (segments are anchored to the scans that saw them);
5. merge into the map (point pairs moved by the laser chain motor; :mod:`.linemap`).

Plain data and pure steps; the caller (CLI, daemon) owns time, threads and I/O.  Poses of the
graph's nodes are laser poses (the laser chain M_GB M_BL with the mount ``M_BL``); the base
pose follows through the inverse mount.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from .cga_segments import laser_motor, segments_to_global
from .correction import Correction, CorrectionParams, correct_pose
from .finishing import FinishJob, NeighbourParams, neighbour_pairs, replace_neighbour_edges
from .free_space import update_streaks
from .line_adjust import AdjustParams, Contributions
from .linemap import LineMap, MapParams, age_out, dedupe, integrate, refresh
from .moving import MovingParams, moved_segments
from .odometry import compose_pose2d as compose
from .odometry import move_points, relative
from .odometry import wrap_angle as wrap
from .posegraph import Column, EdgeArrays, PoseGraph
from .relocalize import Hypothesis, RelocParams, inlier_fraction, relocalize, rivals
from .segments import SegmentParams, Segments, extract_segments
from .slip import SlipParams, recover


def invert(p) -> np.ndarray:
    return relative(np.asarray(p, float), np.zeros(3))


@dataclass(frozen=True)
class LoopParams:
    enabled: bool = True
    every: int = 3                # try closing loops on every n-th scan
    min_separation: int = 10      # scans between a node and the visits it may close with
    min_travel: float = 12.0      # ... and metres of travel (dense and sparse logs alike)
    radius: float = 6.0           # look for earlier visits within this distance (m)
    candidates: int = 2           # earlier visits tried per scan (nearest, nearest older)
    older_gap: int = 50           # "older" means this many scans before the nearest visit
    window: int = 4               # an earlier visit's submap: its scan +- window scans
    # ... and once more with this many when that gives no closure (0: never), while the
    # scan itself tracks the map poorly (matched share under ``wide_below``): at the end of
    # a long corridor mapped once, the few scans around the earlier visit can show too
    # little of what the scan sees.  Intel with the slip recovery, mean ATE: high odometry
    # noise (seeds 0-15) 0.0647 -> 0.0593 m; low noise (seeds 0-3) 0.0468 -> 0.0472 m; the
    # log's own odometry 0.046 -> 0.045 m.  Tried on every failed closure instead: high
    # 0.0591 m, but low 0.0516 m and the log's own 0.054 m
    wide_window: int = 10
    wide_below: float = 0.6
    # an earlier visit that faced the other way (over 90 degrees apart) saw what lies behind
    # the robot now: its submap then also takes that pass's scans taken ahead of the robot
    # (within ``view_range``, at most ``view_back`` behind it, at most ``view_nodes`` on
    # either side of the visit: a dense log's submap stays small), which looked back at the
    # walls this scan sees.  Simulated office, one lap (every corridor revisited the other
    # way), seeds 0-7: ATE mean 0.23 -> 0.14 m; with the corridor end points (``reloc``
    # below) 0.12 m, and Intel seeds 0-15 0.0604 -> 0.0589 m; with the local search, 0.08 m
    # (0.096 m without this submap: half the closures)
    view_range: float = 8.0
    view_back: float = 1.0
    view_nodes: int = 40
    min_score: float = 0.6        # fraction of the scan's points on the submap
    ambiguity: float = 0.08       # no other pose may score within this of the best
    # ... nor may more than this share of its beams pass through the submap's walls (free
    # space where the earlier visit saw walls).  Every closure 0.3 m or more from the truth
    # or the reference with such a share was wrong: Intel seeds 0-3, node 366 (1 m along a
    # corridor: 0.35-0.65), the simulated office's T-junction (4 m: 0.78); of the right ones
    # none had more than 0.17 (201 on Intel, 36 in the office and the long corridor)
    max_crossing: float = 0.3
    # the relocalisation verifies only candidates within this many times (max_jump,
    # max_turn) of the mapper's pose (0: all): in a corridor the submap's look-alike places
    # metres away otherwise crowd the true one out of the few refined hypotheses, while
    # those just beyond a jump still count as rivals (ambiguous).  Office one lap, seeds
    # 0-7: 0.12 -> 0.08 m mean (at 1x: 0.09 m, but one seed 0.22 m, a look-alike farther
    # than the band accepted)
    search: float = 2.0
    max_jump: float = 3.0         # the closure may move the pose by at most this (m) ...
    max_turn: float = np.deg2rad(25.0)  # ... and turn it by at most this
    # ... plus this share of the odometry travel since the chain was last tied to the map (the
    # later of the earlier visit and the last closure), and the earlier visits looked for
    # reach as much farther than ``radius``: a scan-matched trajectory drifts with the
    # distance it goes untied.  MIT Killian Court (1.9 km, revisits 150-700 m apart) with
    # the log's own increments: ATE 8.4 -> 0.53 m (0.02: no change, the first long revisit
    # 4.6 m off); high noise, seeds 0-2: 9.0 / 2.5 / 1.8 -> 4.2 / 0.59 / 0.55 m.  Intel
    # (seeds 0-9), the dense office and the simulated worlds: unchanged (office one lap,
    # seeds 0-7: mean 0.0827 -> 0.0823 m)
    drift_jump: float = 0.03
    # once the allowance reaches this (m), a scan that neither nearby visit could place is
    # relocalised in all the earlier visits within the allowance (+ ``region_margin``) at
    # once (0: never).  After 100 m and more untied, the nearest earlier node (by the
    # drifted pose) is seldom the true one, and its few scans may hold only a look-alike
    # of the place: Killian Court, high noise, seed 0 closed 13 m off onto a repeat of the
    # building's corridors (ATE 4.2 m).  Over the whole region the look-alikes rival the
    # true place and the closure is refused as ambiguous, or the true place wins: seeds
    # 0-2 4.2 / 0.59 / 0.55 -> 0.58 / 0.59 / 0.48 m, low noise 2.7 -> 0.57 m, its own
    # increments 0.53 -> 0.55 m.  Intel never gets that far untied (seeds 0-3 unchanged)
    region_reach: float = 6.0
    region_margin: float = 2.0
    sigma: tuple[float, float] = (0.05, 0.01)  # loop edge std (m, rad)
    confirm: bool = True          # a relocalised closure is refined and must still fit
    # ... and match the scan about as well as the current pose refined the same way: it is
    # refused when that matches this share of the scan's length more (None: no check)
    guess_margin: float | None = 0.05
    # when the two match alike (within guess_margin), the submap cannot tell them apart: the
    # jump is then refused beyond this (m) plus this share of the odometry travel since the
    # chain was last tied to the map: the later of the earlier visit and the last closure
    # (the drift a scan-matched trajectory may have gathered meanwhile)
    tie_jump: tuple[float, float] = (0.3, 0.03)
    # a closure that moves the pose farther than this (m) plus ``drift_jump`` of the travel
    # since the chain was last tied, and of the travel over the pose graph from the earlier
    # visit (:meth:`Mapper._graph_travel`), is held, not taken, until another scan's closure
    # agrees with it (to ``agree``: m, rad, after the chain's motion between the two): the
    # newest earlier node's, relocalised in the same submap at once, or the next one within
    # ``hold_nodes`` nodes.  One that disagrees, or none, and it goes (0: never held, the
    # default).  A look-alike stretch of corridor in a small submap can fit a scan better
    # than the true place (Intel, high noise: five seeds of eight took one 2.3 m closure at
    # scan 533, 8 m over the graph from its visit).  Measured at 1.0 (docs/mapping-2d.md,
    # *A far jump held for a second scan*): the Intel robot's own wheels 0.0887 -> 0.0759 m
    # mean, worst 0.143 -> 0.085 m; Intel high noise 0.0588 -> 0.0585 m; Killian Court
    # 0.565 -> 0.533 m mean of four runs; but a sparse log's first loop (4-5 m of drift in
    # 75 m) waits for a second scan, and a look-alike there may refute it: Intel thinned to
    # every 2nd scan 0.0873 -> 0.0901 m, every 3rd 0.455 -> 0.636 m
    confirm_jump: float = 0.0
    hold_nodes: int = 12
    agree: tuple[float, float] = (0.3, np.deg2rad(3.0))
    optimize_trans: float = 0.04  # re-optimise when a closure disagrees by more than this
    optimize_rot: float = 0.01    # (rad)
    cooldown: int = 3             # scans between optimisations ...
    cooldown_travel: float = 2.0  # ... and metres (a dense log must not re-solve every scan)
    # the optimisation while mapping solves the newest ``online_window`` nodes; the older
    # ones stay put, held where a closure ties to them (the finishing pass solves them
    # all).  A daemon's graph of 20 000 nodes must not cost every closure a whole solve
    online_window: int = 2000
    quiet_after: int = 4          # scans without attempts after a closure that agreed
    sweep_every: int = 2          # after the run: tracking closures on every n-th scan (0: off)
    sweep_radius: float = 2.0     # ... with the nearest earlier visit within this (m)
    max_std: float = 0.06         # tracking closure: translation std in every direction (m)
    tracking_score: float = 0.75  # tracking closure: fraction of scan points on the submap
    tracking: CorrectionParams = field(default_factory=lambda: CorrectionParams(
        gates=(1.0, 0.6, 0.4, 0.25, 0.15, 0.1, 0.08),
        angle_gates_deg=(20.0, 12.0, 8.0, 5.0, 4.0, 3.0, 3.0)))


# the prior of a tracked scan's correction on the finished map (m, as an odometry step):
# loose, the walls decide.  The dense 5 cm loop's tracked scans: 4.0 / 2.7 / 2.1 mm RMS with
# 0.1 / 0.5 / 2 (its nodes 2.3 mm; 5.4 mm not placed again); the hall's (a scan every 0.5 m,
# a third of them tracked): 20 / 16 / 16 mm, one of them 18-19 cm off with any
PLACE_STEP = 0.5


@dataclass
class MapperParams:
    segments: SegmentParams = field(default_factory=SegmentParams)
    # one gate tighter than the correction's default (0.06 m, 2.5 deg): the last pass
    # leaves clutter and the neighbouring wall out of a scan-to-map step
    correction: CorrectionParams = field(default_factory=lambda: CorrectionParams(
        gates=(0.4, 0.25, 0.15, 0.1, 0.08, 0.06),
        angle_gates_deg=(15.0, 9.0, 5.0, 4.0, 3.0, 2.5)))
    map: MapParams = field(default_factory=MapParams)
    loop: LoopParams = field(default_factory=LoopParams)
    neighbours: NeighbourParams = field(default_factory=NeighbourParams)
    reloc: RelocParams = field(default_factory=lambda: RelocParams(
        min_score=0.6, refine=10, endpoint_lines=0, corridor_endpoint_lines=6,
        fit_weight=0.0, sweep_cells=0))
    # loop closures: no sweep (the submap is small, the guess close); a corridor scan's
    # positions along it from its lines' end points (its lines pair with no cross line),
    # and the best 10 kept, so look-alikes count as rivals
    mount: tuple[float, float, float] | None = None  # laser pose in the base frame (M_BL)
    seq_sigma: tuple[float, float] = (0.03, 0.008)   # matched step: (m, rad)
    seq_from_cov: bool = False  # add the correction's covariance to seq_sigma
    odo_sigma: tuple[float, float, float, float] = (0.05, 0.10, 0.02, 0.03)  # unmatched step
    # a scan the odometry put beyond the correction's reach (wheel slip, a push, a turn's
    # heading error): found again from the walls' directions (:mod:`.slip`); such a step
    # teaches the odometry calibration nothing
    slip: SlipParams = field(default_factory=SlipParams)
    # a scan's segments where a scan a moment earlier saw through are not mapped: people
    # and carts on the move (:mod:`.moving`)
    moving: MovingParams = field(default_factory=MovingParams)
    # after the neighbour pass: poses and the map's walls solved together (:mod:`.line_adjust`)
    adjust: AdjustParams = field(default_factory=AdjustParams)
    # online odometry calibration: heading drift per metre and translation scale, learnt from
    # the corrections of well-matched steps (exponential average with this weight)
    calib_rate: float = 0.05
    calib_min_fraction: float = 0.5
    # a long run (the daemon): past this many graph nodes the oldest are dropped (0: never);
    # their map segments stay and still serve for matching, frozen where they are
    max_nodes: int = 0
    # a scan becomes a graph node (merged into the map, a closure candidate) once the
    # odometry has moved ``node_travel`` (m) or turned ``node_turn`` (rad) since the last
    # node; one taken sooner is only tracked against the map, unless under ``node_below``
    # of it matches (new ground: it is mapped).  A scan stream ten times denser than a
    # metre apart then builds the graph a sparse log would (0, 0: every scan a node).
    # Tracked scans are placed again on the finished map (``place``)
    node_travel: float = 0.5
    node_turn: float = 0.2
    node_below: float = 0.5
    # ... or when its correction moved it farther from the odometry's prediction than this
    # many of the prior's sigmas (Mahalanobis): walls that disagree with the wheels are for
    # the graph to judge, where a tracked scan's one correction would stand
    node_surprise: float = 2.0


@dataclass
class StepResult:
    pose: np.ndarray          # corrected laser pose (x, y, theta)
    segments: int
    correction: Correction | None
    loops: int = 0
    optimized: bool = False
    # the graph node this scan became, or was tracked from (numbered as ``Mapper.dropped``
    # plus the graph index), and the scan's pose relative to it (zero for a node)
    node: int = -1
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))


class Mapper:
    """State of one mapping run: the line map, the pose graph, the last odometry pose."""

    def __init__(self, params: MapperParams | None = None, initial_pose=(0.0, 0.0, 0.0)):
        self.params = params or MapperParams()
        self._map = LineMap()
        self.anchors = [0]   # nodes held fixed in the graph: the start and every re-anchor
        self.graph = PoseGraph()
        self.initial = np.asarray(initial_pose, dtype=float)
        self.last_odom: np.ndarray | None = None   # at the last node
        # the last tracked scan since that node: its odometry and pose relative to the node
        self._tracked: tuple[np.ndarray, np.ndarray] | None = None
        self.last_opt = -10 ** 9
        self.pending = False
        self.loops = 0
        self.optimizations = 0
        self.last_loop = -10 ** 9
        self.last_aged = -10 ** 9  # the node the map's short segments were last judged at
        # odometry distance from the start, per node (an array: each scan searches it)
        self.travel = Column((), float)
        # per node: its raw odometry step (x, y, theta), the calibration (scale, drift) it
        # was predicted with, which the finishing pass re-estimates (:func:`_recalibrate`),
        # the step's length for the prior and the heading it was predicted from ...
        self.odo_step = Column((7,), float)
        # ... and the corrected pose's covariance: with those, how much of its prediction
        # the pose kept (:func:`prediction_shares`, once per pass, not per scan)
        self.odo_cov = Column((3, 3), float)
        self.stepped = 0                    # scans stepped so far, nodes or tracked ...
        self.node_scan = Column((), int)    # ... and per node, which of them it was
        self.calibration: dict = {}  # the last finishing pass's estimate
        self.calib_n = 0
        self.slips = 0           # scans recovered from a slip (:mod:`.slip`)
        self.cleared = 0         # map segments the laser saw through, dropped (:mod:`.free_space`)
        self.moved = 0           # scan segments not mapped: they had moved in (:mod:`.moving`)
        # the last scans (the same chain only), for :mod:`.moving`, by scan number
        # (``stepped``), tracked ones too: (node, offset from it or None, odometry travel,
        # ranges, angle_min, angle_increment)
        self._recent: dict[int, tuple] = {}
        # the last scan whose correction matched mostly frozen map segments (created before
        # this run's nodes): the free-space test's tie for them (:mod:`.free_space`)
        self.frozen_tie = -10 ** 9
        # whether the map may hold frozen segments at all (set on adopting a map and on
        # compacting): most runs have none, and then no scan need look for them
        self._frozen = False
        self.drift_per_m = 0.0   # learnt odometry heading drift (rad/m)
        self.scale = 1.0         # learnt ratio of true to odometry distance
        self.scans: list[tuple[np.ndarray, np.ndarray]] = []  # per node: segments a, b
        # contributions (node, a, b) of segments aged out as glimpses, by node: a closure's
        # submap of that place still has them (aging judges what the map keeps for good;
        # a dense run's short-lived pieces were all a closure had of its loop's start)
        self._retired = (np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2)))
        # the finishing pass needs each node's own segments: kept when the pass is enabled,
        # or when the owner asks (the daemon runs the pass on demand, :meth:`finishing_job`)
        self.keep_scans = self.params.neighbours.enabled or (
            self.params.loop.enabled and self.params.loop.sweep_every > 0)
        self.neighbour_edges = 0
        self.sweep_edges = 0  # tracking closures of the last finishing pass's sweep
        self.round_moves: list = []  # ... and how far each of its rounds moved the map (m)
        self.adjusted: dict = {}  # the line adjustment's figures (lines, observations, ...)
        self.dropped = 0  # nodes dropped by :meth:`compact` so far (node numbers shift)
        # nodes before this one were placed by the last adopted finishing pass: the online
        # optimisation leaves them there (it re-solved them with the pass's hundreds of
        # thousands of edges, 1.2 s a closure, where the newer nodes alone take milliseconds)
        self.finished_upto = 0
        # the graph's edges before this one were weighed by an earlier solve: the online
        # optimisation's graduated first iterations trust only the newer closures
        self._judged = 0
        # the graph's edges [n0, n1) are the last neighbour pass's; the scan-to-map edges
        # before ``_weighted`` already count NeighbourParams.sequential_weight
        self._neighbour_block = (0, 0)
        self._weighted = 0
        self.loop_stats = {"tracked": 0, "tried": 0, "no_pose": 0, "low_score": 0,
                           "unconfirmed": 0, "guess_fits": 0, "wide_tried": 0,
                           "ambiguous": 0, "sees_through": 0, "region_tried": 0,
                           "region": 0, "held": 0, "held_confirmed": 0,
                           "held_dropped": 0, "witnessed": 0}
        # closures of one scan that jumped too far, waiting for a later one: (j, i, z, guess)
        self._held: list[tuple] = []

    @property
    def map(self) -> LineMap:
        return self._map

    @map.setter
    def map(self, lmap: LineMap) -> None:
        """Adopt a map (e.g. loaded from a checkpoint): contributions from scans that are not
        this run's graph nodes are frozen (node -1), so they are neither moved nor matched
        as an earlier visit, while their segments still serve for matching.  The segments'
        scan stamps (``created``, ``last_seen``) shift to before this run's first node,
        keeping their spacing: counted in another run's numbers they would lie in this
        run's future (never aged, always "recent" to the duplicate check, and no drift
        allowance for the free-space test until this run caught up)."""
        if lmap is not self._map:
            if len(lmap.c_node):
                lmap.c_node = np.full_like(lmap.c_node, -1)
            if len(lmap):
                self._frozen = True
                shift = int(lmap.last_seen.max()) + 1
                if shift > 0:
                    lmap.created = lmap.created - shift
                    lmap.last_seen = lmap.last_seen - shift
        self._map = lmap

    @property
    def count(self) -> int:
        return len(self.graph.poses)

    @property
    def poses(self) -> np.ndarray:
        return np.array(self.graph.poses) if self.graph.poses else np.zeros((0, 3))

    @property
    def pose(self) -> np.ndarray:
        """The laser pose of the last scan: the last node's, or the scan tracked since."""
        if not self.count:
            return self.laser_pose(self.initial)
        last = self.graph.poses[-1]
        return last.copy() if self._tracked is None else compose(last, self._tracked[1])

    def laser_pose(self, base_pose) -> np.ndarray:
        m = self.params.mount
        return np.asarray(base_pose, float) if m is None else compose(base_pose, m)

    def base_pose(self, laser_pose) -> np.ndarray:
        m = self.params.mount
        return np.asarray(laser_pose, float) if m is None else compose(laser_pose, invert(m))

    def step(self, ranges, angle_min: float, angle_increment: float, odom) -> StepResult:
        """One scan with its odometry (base) pose: predict, correct against the global map,
        add to the pose graph, close loops, merge into the map."""
        P = self.params
        odom_l = self.laser_pose(odom)
        seg = extract_segments(ranges, angle_min, angle_increment, P.segments)
        corr = None
        self.stepped += 1
        if self.last_odom is None:
            # first scan, or re-anchored (set pose): a new chain held at the given pose
            pose = self.laser_pose(self.initial)
            i = self.graph.add_node(pose)
            if i and i not in self.anchors:
                self.anchors.append(i)
            self.travel.append(self.travel[-1] if len(self.travel) else 0.0)
            self.node_scan.append(self.stepped - 1)
            self.odo_step.append((0.0, 0.0, 0.0, self.scale, self.drift_per_m, 0.0, 0.0))
            self.odo_cov.append(np.zeros((3, 3)))
            self.last_odom = odom_l
            self._tracked = None
            self._recent.clear()  # a new chain: the last scans' poses are not tied to it
            self._remember(i, None, self.travel[i], ranges, angle_min, angle_increment)
            self._merge(seg, i, None, abs(angle_increment))
            return StepResult(pose, len(seg), None, node=self.dropped + i)
        raw = relative(self.last_odom, odom_l)
        d_odo = float(np.hypot(raw[0], raw[1]))
        prev = self.graph.poses[-1]
        # predicted from the last tracked scan: the map has corrected the odometry up to it
        pred = self._predict(odom_l)
        # the prior's step counts from the last node: with a tight prior per tracked step, a
        # chain of them lagged the walls (dense 5 cm loop, online: 22 mm against 5 mm)
        reach = d_odo + 0.3 * abs(float(raw[2]) - self.drift_per_m * d_odo)
        if len(self.map) and len(seg):
            corr = correct_pose(seg, self.map.a, self.map.b, pred, reach, P.correction)
            # how far the walls moved the pose from the odometry's, in the prior's sigmas
            dz = corr.pose - pred
            dz[2] = wrap(dz[2])
            surprise = float(P.correction.prior_information(reach) @ (dz * dz))
            if (d_odo < P.node_travel and abs(raw[2]) < P.node_turn
                    and corr.matched_fraction >= P.node_below
                    and surprise <= P.node_surprise ** 2):
                self._tracked = (odom_l, relative(prev, corr.pose))
                self._remember(self.count - 1, self._tracked[1], self.travel[-1] + d_odo,
                               ranges, angle_min, angle_increment)
                return StepResult(corr.pose, len(seg), corr, node=self.dropped + self.count - 1,
                                  offset=self._tracked[1].copy())
        self.last_odom = odom_l
        self._tracked = None
        scale, drift = self.scale, self.drift_per_m
        step = reach
        pose = pred
        cov = None  # no correction: the pose is the prediction
        if corr is not None:
            slipped = None
            if P.slip.enabled and corr.matched_fraction < P.slip.below:
                slipped = recover(seg, self.map.a, self.map.b, pred, corr, P.correction,
                                  P.slip)
                if slipped is not None:
                    corr = slipped
                    self.slips += 1
            pose = corr.pose
            if slipped is None:
                self._tie_frozen(len(self.graph.poses), seg, corr)
            # a slip's pose owes nothing to the prediction
            cov = np.zeros((3, 3)) if slipped is not None else corr.cov
            if (slipped is None and corr.matched_fraction >= P.calib_min_fraction
                    and d_odo > 0.2):
                got = relative(prev, pose)
                self.calib_n += 1
                a = max(P.calib_rate, 1.0 / self.calib_n)  # a plain mean until the EMA takes over
                self.drift_per_m += a * (float(wrap(raw[2] - got[2])) / d_odo - self.drift_per_m)
                self.scale += a * (float(np.hypot(got[0], got[1])) / d_odo - self.scale)
        i = self.graph.add_node(pose)
        self.travel.append(self.travel[-1] + d_odo)
        self.node_scan.append(self.stepped - 1)
        self.odo_step.append((*raw, scale, drift, step, prev[2]))
        self.odo_cov.append(cov if cov is not None else
                            np.diag(1.0 / P.correction.prior_information(step)))
        if corr is not None and corr.matched_fraction > 0.3:
            st, sr = P.seq_sigma
            if P.seq_from_cov:
                # the correction's own covariance, in the previous pose's frame: a corridor
                # step is only known across the corridor
                c, s_ = np.cos(prev[2]), np.sin(prev[2])
                Rt = np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]])
                cov = Rt @ corr.cov @ Rt.T + np.diag([st ** 2, st ** 2, sr ** 2])
                info = np.linalg.inv(cov)
            else:
                info = np.diag([st ** -2, st ** -2, sr ** -2])
        else:
            a, b, c, d = P.odo_sigma
            st, sr = a + b * step, c + d * step
            info = np.diag([st ** -2, st ** -2, sr ** -2])
        self.graph.add_edge(i - 1, i, relative(prev, pose), info)
        loops, optimized = 0, False
        if P.loop.enabled:
            loops = self._close_loops(i, seg, 0.0 if corr is None else corr.matched_fraction)
            since = self.travel[i] - self.travel[max(self.last_opt, 0)]
            if self.pending and i - self.last_opt >= P.loop.cooldown and (
                    self.last_opt < 0 or since >= P.loop.cooldown_travel):
                self.optimize()
                optimized = True
        # the correction already found the map segments near this scan (unless an
        # optimisation has just moved the map)
        near = corr.near if corr is not None and not optimized else None
        n_seg = len(seg)
        seg = self._without_movers(i, seg)
        self._remember(i, None, self.travel[i], ranges, angle_min, angle_increment)
        self._merge(seg, i, near, abs(angle_increment))
        pose = self.graph.poses[i].copy()
        if P.max_nodes and self.count > P.max_nodes:
            self.compact(max(P.max_nodes * 9 // 10, 1))
        return StepResult(pose, n_seg, corr, loops, optimized, node=self.dropped + self.count - 1)

    def place(self, ranges, angle_min: float, angle_increment: float, guess) -> np.ndarray:
        """A scan's laser pose corrected against the map as it is now, from ``guess`` (a
        tracked scan's pose once its node has moved: the map it was tracked against has moved
        with the closures since); the guess when under ``node_below`` of the scan matches."""
        P = self.params
        guess = np.asarray(guess, dtype=float)
        seg = extract_segments(ranges, angle_min, angle_increment, P.segments)
        if not len(seg) or not len(self.map):
            return guess
        corr = correct_pose(seg, self.map.a, self.map.b, guess, PLACE_STEP, P.correction)
        return corr.pose if corr.matched_fraction >= P.node_below else guess

    def _predict(self, odom_l: np.ndarray) -> np.ndarray:
        """The scan's pose predicted by the calibrated odometry from the last tracked scan
        (or the last node): the map has corrected the odometry up to it."""
        base_odom, off = self._tracked if self._tracked is not None else (self.last_odom, None)
        raw = relative(base_odom, odom_l)
        d = float(np.hypot(raw[0], raw[1]))
        inc = np.array([raw[0] * self.scale, raw[1] * self.scale, raw[2] - self.drift_per_m * d])
        base = self.graph.poses[-1] if off is None else compose(self.graph.poses[-1], off)
        return compose(base, inc)

    def _retire(self, got: list) -> None:
        """Keep the contributions of segments aged out as glimpses (``MapParams.age_seen``)
        for the loop closures' submaps, in node order."""
        new = [np.concatenate([r[k] for r in got]) for k in range(3)]
        # the new rows are of the last few dozen nodes: only the kept rows from the first
        # of them on are sorted again (a long dense run retires thousands of rows)
        k = int(np.searchsorted(self._retired[0], new[0].min(), side="right"))
        tail = [np.concatenate([old[k:], add]) for old, add in zip(self._retired, new,
                                                                       strict=True)]
        order = np.argsort(tail[0], kind="stable")
        self._retired = tuple(np.concatenate([old[:k], t[order]])
                              for old, t in zip(self._retired, tail, strict=True))

    def _tie_frozen(self, i: int, seg: Segments, corr: Correction) -> None:
        """Scan i is tied to the frozen segments when its correction matched at least
        ``calib_min_fraction`` of its length to them."""
        j = corr.matches
        if (not self._frozen or corr.total_length <= 0 or len(j) != len(seg)
                or not (j >= 0).any()):
            return
        frozen = np.zeros(len(j), bool)
        frozen[j >= 0] = self.map.created[j[j >= 0]] < 0
        if seg.length[frozen].sum() >= self.params.calib_min_fraction * corr.total_length:
            self.frozen_tie = i

    def _remember(self, node: int, offset: np.ndarray | None, travel: float, ranges,
                  angle_min: float, angle_increment: float) -> None:
        """Keep this scan (a node, or tracked from ``node`` at ``offset``) for the scan
        differencing of the next ones."""
        P = self.params.moving
        if not P.enabled:
            return
        # a copy: a driver may fill the same buffer again
        self._recent[self.stepped] = (node, offset, float(travel), np.array(ranges, dtype=float),
                                      float(angle_min), float(angle_increment))
        for k in [k for k in self._recent if k < self.stepped - P.gap_scans]:
            del self._recent[k]

    def _without_movers(self, i: int, seg: Segments) -> Segments:
        """``seg`` (node i's, laser frame, the scan just stepped) without the segments that
        moved in since the newest scan, node or tracked, at least ``gap_travel`` m or
        ``gap_scans`` scans before it (in a chain's first scans, since its oldest)."""
        P = self.params.moving
        if not P.enabled or not len(seg) or not self._recent:
            return seg
        now, t = self.stepped, self.travel[i]
        earlier = [k for k in self._recent if k < now]
        if not earlier:
            return seg
        # the newest far enough back, else the oldest there is (a chain's first scans)
        k = max((k for k in earlier if t - self._recent[k][2] >= P.gap_travel
                 or k <= now - P.gap_scans), default=min(earlier))
        node, off, _, *scan = self._recent[k]
        then = self.graph.poses[node] if off is None else compose(self.graph.poses[node], off)
        pose = self.graph.poses[i]
        moved = moved_segments(move_points(seg.a, pose), move_points(seg.b, pose), then, *scan, P)
        if not moved.any():
            return seg
        self.moved += int(moved.sum())
        return seg.subset(~moved)

    def compact(self, keep: int) -> int:
        """Keep the newest ``keep`` nodes of the graph; returns how many went.

        The map keeps every segment: the dropped scans' contributions are forgotten, so a
        segment seen only by them stays frozen where it is (as an adopted map's do) and one
        also seen later follows its later scans.  Edges to dropped nodes go, and the oldest
        kept node is held fixed where it is.  Node numbers (and the map's scan stamps) shift
        down by the number dropped."""
        cut = self.count - keep
        if cut <= 0:
            return 0
        self._frozen = True  # the dropped scans' segments stay, frozen
        g, m = self.graph, self.map
        live = m.c_node >= cut
        for name in ("c_seg", "c_node", "c_n", "c_cent", "c_scat", "c_a", "c_b"):
            setattr(m, name, getattr(m, name)[live])
        m.c_node = m.c_node - cut
        m.created = m.created - cut
        m.last_seen = m.last_seen - cut
        ei, ej = g.ei.array(), g.ej.array()
        kept = np.nonzero((ei >= cut) & (ej >= cut))[0]
        g.poses = g.poses[cut:]
        g.ei, g.ej = ei[kept] - cut, ej[kept] - cut
        for name in ("z", "info", "loop"):
            setattr(g, name, getattr(g, name)[kept])
        self.anchors = sorted({0, *(a - cut for a in self.anchors if a >= cut)})
        self.travel = Column((), float, self.travel[cut:])
        self.node_scan = Column((), int, self.node_scan[cut:])
        self.odo_step = Column((7,), float, self.odo_step[cut:])
        self.odo_cov = Column((3, 3), float, self.odo_cov[cut:])
        self.scans = self.scans[cut:]  # the finishing pass's segments go with their nodes
        # edge numbers of the neighbour block shift with the edges dropped before them
        n0, n1 = self._neighbour_block
        self._neighbour_block = (int(np.searchsorted(kept, n0)), int(np.searchsorted(kept, n1)))
        self._weighted = int(np.searchsorted(kept, self._weighted))
        self._judged = int(np.searchsorted(kept, self._judged))
        self.dropped += cut
        self.last_opt -= cut
        self.last_loop -= cut
        self._held = []
        self.last_aged -= cut
        self._recent = {k: (v[0] - cut, *v[1:]) for k, v in self._recent.items() if v[0] >= cut}
        rn, ra, rb = self._retired
        self._retired = (rn[rn >= cut] - cut, ra[rn >= cut], rb[rn >= cut])
        self.frozen_tie -= cut
        self.finished_upto = max(self.finished_upto - cut, 0)
        return cut

    def _merge(self, seg: Segments, node: int, near: np.ndarray | None,
               beam_step: float | None = None) -> None:
        P = self.params
        if self.keep_scans and len(self.scans) == node:
            self.scans.append((seg.a, seg.b))
        M = laser_motor(self.graph.poses[node])
        seg_g = segments_to_global(seg, M)
        integrate(self.map, seg_g, node, P.map, seg_l=seg, node=node, candidates=near)
        if P.map.clear.enabled and node % max(P.map.clear.every, 1) == 0:
            # a closure ties the laser to the old map, once a solve applied it if it
            # disagreed (pending); a scan matched well to the frozen segments (an adopted
            # map's, or those of nodes compacted away) ties it to them: they do not move
            tie = self.last_opt if self.pending else self.last_loop
            tied = (np.where(self.map.created < 0, max(tie, self.frozen_tie), tie)
                    if self.frozen_tie > tie else tie)
            update_streaks(self.map, self.graph.poses[node][:2], seg_g.points, node,
                           P.map.clear, self.travel.array(), tied, beam_step)
        if node - self.last_aged >= max(P.map.age_every,
                                        len(self.map.c_seg) // P.map.age_rows):
            if P.map.clear.enabled:
                self.cleared += int(np.count_nonzero(self.map.through >= P.map.clear.scans))
            got: list = []
            # the odometry's turn so far (rad, absolute), from each node's raw step
            turned = np.cumsum(np.abs(self.odo_step.array()[:, 2]))
            age_out(self.map, node, P.map, self.travel.array(), turned, got)
            if got:
                self._retire(got)
            self.last_aged = node
        if node % P.map.dedupe_every == 0:
            dedupe(self.map, P.map, since=node - P.map.dedupe_every)

    def _close_loops(self, i: int, seg: Segments, tracking: float) -> int:
        """Match scan i against the segments of an earlier visit (its scans +- window, in
        that visit's frame) by Hough-domain relocalisation (§V), so drift of metres and
        degrees is still caught; an unambiguous, well-scoring result becomes a loop edge.
        ``tracking``: the scan's matched share against the map (the wider submap is tried
        only under ``LoopParams.wide_below``)."""
        LP = self.params.loop
        self._expire_held(i)
        last = self._last_old(i)
        if last < 0 or len(seg) < 2 or not len(self.map.c_node):
            return 0
        if i % LP.every:
            return 0
        if i - self.last_loop <= LP.quiet_after and not self.pending:
            return 0  # just closed with a small disagreement: still on the old map
        X = self.poses
        old = X[: last + 1]
        dist = np.linalg.norm(old[:, :2] - X[i, :2], axis=-1)
        order = np.argsort(dist)
        tried, added = [], 0
        reach = self._reach(i, self.last_loop)
        near = order[dist[order] <= LP.radius + reach - LP.max_jump]
        # the nearest earlier visit, then the nearest of clearly older visits: ties to the
        # oldest parts of the map keep the whole trajectory consistent
        picks = []
        if len(near):
            picks.append(int(near[0]))
            older = near[near < picks[0] - LP.older_gap]
            if len(older) and LP.candidates > 1:
                picks.append(int(older[0]))
        for j in picks:
            tried.append(int(j))
            sub = self._submap(X, j, last, span=self._facing(X, i, j, last))
            if sub is None:
                continue
            guess = relative(X[j], X[i])
            best = self._closure_by_tracking(seg, sub, guess)
            if best is not None:
                self.loop_stats["tracked"] += 1
            else:
                best = self._closure_by_relocalising(seg, sub, guess, i, j)
                wide = self._submap(X, j, last, LP.wide_window) if (
                    best is None and LP.wide_window > LP.window
                    and tracking < LP.wide_below) else None
                if wide is not None:
                    # the earlier visit's few scans may show too little of what this scan
                    # sees to place it: once more against more of that visit
                    self.loop_stats["wide_tried"] += 1
                    best = self._closure_by_relocalising(seg, wide, guess, i, j)
                if best is None:
                    continue
            added += self._take_closure(int(j), i, best.pose, guess)
        if not added and LP.region_reach and reach >= LP.region_reach:
            region = near[dist[near] <= reach + LP.region_margin]
            sub = self._submap(X, int(region[0]), last, nodes=region) if len(region) else None
            if sub is not None:
                j = int(region[0])
                self.loop_stats["region_tried"] += 1
                guess = relative(X[j], X[i])
                best = self._closure_by_relocalising(seg, sub, guess, i, j)
                if best is not None:
                    self.loop_stats["region"] += 1
                    added += self._take_closure(j, i, best.pose, guess)
        return added

    def _take_closure(self, j: int, i: int, z: np.ndarray, guess: np.ndarray) -> int:
        """Add loop edge j -> i measuring ``z``, unless it jumps beyond ``confirm_jump`` and
        the drift allowance (of both the travel since the chain was last tied and the
        travel over the graph from j): then it is held, and the newest earlier node's scan
        is relocalised in the same submap as a witness.  Held closures are added when the
        witness or the first closure of a later scan agrees with them and dropped when it
        does not (the later closure is then taken on its own terms).  Another closure of
        the same scan that agrees joins them: the scan, not its submap, is what may be a
        look-alike.  Returns the edges added."""
        LP = self.params.loop
        held = self._held
        X = self.graph.poses
        if held:
            if not self._agrees(held[0], X[i], compose(X[j], z)):
                self.loop_stats["held_dropped"] += len(held)
                self._held = []
            elif held[0][1] == i:
                self.loop_stats["held"] += 1
                held.append((j, i, z, guess))
                return 0
            else:
                return self._confirm(j, i, z, guess)
        jump = float(np.hypot(*relative(guess, z)[:2]))
        if (LP.confirm_jump > 0 and jump > LP.confirm_jump + LP.drift_jump * self._untied(i, j)
                and jump > LP.confirm_jump + LP.drift_jump * self._graph_travel(i, j)):
            self.loop_stats["held"] += 1
            self._held = [(j, i, z, guess)]
            witness = self._earlier_witness(j, i)
            if witness is None:
                return 0
            if self._agrees(self._held[0], *witness):
                self.loop_stats["witnessed"] += 1
                return self._confirm()
            self.loop_stats["held_dropped"] += 1
            self._held = []
            return 0
        self._add_closure(j, i, z, guess)
        return 1

    def _confirm(self, *new) -> int:
        """Add the held closures and ``new`` (j, i, z, guess) if given; returns how many."""
        held, self._held = self._held, []
        self.loop_stats["held_confirmed"] += len(held)
        for h in held:
            self._add_closure(*h)
        if new:
            self._add_closure(*new)
        return len(held) + bool(new)

    def _earlier_witness(self, j: int, i: int):
        """The newest earlier node's scan at least 0.4 m of travel back (kept for
        :mod:`.moving`), relocalised in visit j's submap from where the chain has it: (its
        chain pose, the pose its closure gives), both in the map frame; None when there is
        no such scan or it finds no closure."""
        X = self.graph.poses
        t = float(self.travel[i])
        ks = [k for k, v in self._recent.items() if v[1] is None and t - v[2] >= 0.4
              and 0 <= v[0] < i and v[0] > j]
        if not ks:
            return None
        node, _, _, ranges, a0, da = self._recent[max(ks)]
        sub = self._submap(self.poses, j, self._last_old(i))
        if sub is None:
            return None
        seg = extract_segments(ranges, a0, da, self.params.segments)
        if len(seg) < 2:
            return None
        got = self._closure_by_relocalising(seg, sub, relative(X[j], X[node]), node, j)
        return None if got is None else (X[node], compose(X[j], got.pose))

    def _agrees(self, held: tuple, at: np.ndarray, placed: np.ndarray) -> bool:
        """Whether a held closure (j, i, z, ...) and a closure of another scan (``at`` in
        the chain, ``placed`` by its closure, both in the map frame) agree, after the
        chain's own motion between the two scans."""
        j, i, z = held[:3]
        X = self.graph.poses
        d = relative(compose(compose(X[j], z), relative(X[i], at)), placed)
        st, sr = self.params.loop.agree
        return bool(np.hypot(d[0], d[1]) <= st and abs(d[2]) <= sr)

    def _expire_held(self, i: int) -> None:
        """Drop held closures that no later scan confirmed within ``hold_nodes`` of node i."""
        if self._held and i - self._held[0][1] > self.params.loop.hold_nodes:
            self.loop_stats["held_dropped"] += len(self._held)
            self._held = []

    def _add_closure(self, j: int, i: int, z: np.ndarray, guess: np.ndarray) -> None:
        """Loop edge j -> i measuring ``z``; a solve is due when it disagrees with the mapper's
        own relative pose ``guess`` by more than the optimisation thresholds."""
        LP = self.params.loop
        st, sr = LP.sigma
        self.graph.add_edge(j, i, z, np.diag([st ** -2, st ** -2, sr ** -2]), loop=True)
        self.loops += 1
        e = relative(guess, z)
        if np.hypot(e[0], e[1]) > LP.optimize_trans or abs(e[2]) > LP.optimize_rot:
            self.pending = True
        self.last_loop = i

    def _closure_by_relocalising(self, seg: Segments, sub: LineMap, guess: np.ndarray,
                                 i: int, j: int) -> Hypothesis | None:
        """Hough relocalisation of scan i in the submap of visit j (its frame), confirmed by
        the correction from there and checked against the pose the mapper has (``guess``);
        None, counted in ``loop_stats`` by the reason, when it is no closure."""
        LP = self.params.loop
        jump = self._reach(i, j)
        res = relocalize(sub, seg, None, self.params.reloc,
                         (guess, LP.search * jump, LP.search * LP.max_turn)
                         if LP.search else None)
        self.loop_stats["tried"] += 1
        near = [h for h in res.hypotheses
                if np.hypot(*(h.pose[:2] - guess[:2])) < jump
                and abs(wrap(h.pose[2] - guess[2])) < LP.max_turn]
        if not near:
            self.loop_stats["no_pose"] += 1
            return None
        if near[0].score < LP.min_score:
            self.loop_stats["low_score"] += 1
            return None
        best = near[0]
        if rivals(res.hypotheses, best, LP.ambiguity):
            self.loop_stats["ambiguous"] += 1
            return None
        if best.crossing > LP.max_crossing:
            # the scan's beams would pass through the walls of the earlier visit there
            self.loop_stats["sees_through"] += 1
            return None
        if not LP.confirm:
            return best
        # the Hough pose is coarse (a near miss of a few degrees bends the map): refined by
        # the point-to-line correction from there, it must still fit
        corr = correct_pose(seg, sub.a, sub.b, best.pose, 1.0, self.params.correction)
        moved = relative(best.pose, corr.pose)
        if corr.matched_fraction < 0.5 or np.hypot(*moved[:2]) > 0.3 or abs(
                moved[2]) > np.deg2rad(5.0):
            self.loop_stats["unconfirmed"] += 1
            return None
        # the drift a jump may undo is what built up since the chain was last tied to the
        # map (by any closure), not since the earlier visit: on Intel the travel since the
        # visit (120 m) let a closure slide a corridor scan 1.1 m from a pose tied 12 scans
        # before, that matched its submap exactly as well
        if self._guess_rivals(seg, sub, guess, corr, LP, self._untied(i, j)):
            self.loop_stats["guess_fits"] += 1
            return None
        return Hypothesis(corr.pose, best.score)

    def _graph_travel(self, i: int, j: int) -> float:
        """The least odometry travel (m) over a path between nodes i and j in the pose graph,
        its loop and neighbour edges counted as none: how far the pose graph lets node i
        drift from node j.  A chain tied by its last closure to a place the graph does not
        tie to j's has drifted from j over the whole way round."""
        n = self.count
        ei, ej = self.graph.ei.array(), self.graph.ej.array()
        # each linked pair once (a sparse matrix adds repeated entries up); consecutive nodes
        # are a step of odometry (never a loop edge: closures are min_separation apart), any
        # other pair none, which a nanometre stands for (a zero entry would be no edge)
        pair = np.sort(np.minimum(ei, ej) * n + np.maximum(ei, ej))
        # (not np.unique: numpy 2.4's takes 0.2 s on a daemon's 320 000 edges, a sort 20 ms)
        first = np.ones(len(pair), bool)
        first[1:] = pair[1:] != pair[:-1]
        a, b = np.divmod(pair[first], n)
        tv = self.travel.array()
        w = np.where(b - a == 1, tv[b] - tv[a], 0.0) + 1e-9
        G = sp.csr_matrix((w, (a, b)), shape=(n, n))
        return float(dijkstra(G, directed=False, indices=i)[j])

    def _untied(self, i: int, j: int) -> float:
        """The odometry travel (m) of node i since the chain was last tied to the map: since
        the later of the earlier node j and the last closure (none when that is after i)."""
        since = max(j, self.last_loop, 0)
        return float(self.travel[i] - self.travel[min(since, i)])

    def _reach(self, i: int, j: int) -> float:
        """How far (m) a closure of node i with earlier node j may move it: ``max_jump`` plus
        ``drift_jump`` of the travel since the later of j and the last closure."""
        LP = self.params.loop
        return LP.max_jump + LP.drift_jump * self._untied(i, j)

    def _last_old(self, i: int) -> int:
        """The newest node that node i may close a loop with (-1: none yet): at least
        ``min_separation`` scans and ``min_travel`` metres of odometry back."""
        LP = self.params.loop
        travel = self.travel.array()
        by_dist = int(np.searchsorted(travel, travel[i] - LP.min_travel, side="right")) - 1
        return min(by_dist, i - LP.min_separation)

    def _facing(self, X: np.ndarray, i: int, j: int, last: int) -> tuple[int, int] | None:
        """When node j faced away from node i (over 90 degrees): the run of j's pass (the
        nodes next to j, up to ``last``) that lies ahead of i, within ``view_range`` and at
        most ``view_back`` behind; those scans looked back at what i sees.  Else None."""
        LP = self.params.loop
        if LP.view_range <= 0 or abs(wrap(X[i, 2] - X[j, 2])) <= np.pi / 2:
            return None
        first, stop = max(j - LP.view_nodes, 0), min(j + LP.view_nodes, last) + 1
        d = X[first:stop, :2] - X[i, :2]
        ahead = (np.hypot(d[:, 0], d[:, 1]) <= LP.view_range) & (
            d @ np.array([np.cos(X[i, 2]), np.sin(X[i, 2])]) >= -LP.view_back)
        ahead[j - first] = True
        out = np.flatnonzero(~ahead) + first  # the run of True through j
        lo = int(out[out < j].max()) + 1 if np.any(out < j) else first
        hi = int(out[out > j].min()) - 1 if np.any(out > j) else stop - 1
        return lo, hi

    def _submap(self, X: np.ndarray, j: int, last: int, window: int | None = None,
                span: tuple[int, int] | None = None,
                nodes: np.ndarray | None = None) -> LineMap | None:
        """The segments seen from scans j +- window (LoopParams.window unless given; none
        after ``last``) and from the nodes ``span`` (first, last) if given, in j's frame;
        ``nodes`` given: those nodes' segments instead."""
        LP = self.params.loop
        window = LP.window if window is None else window
        # contributions are kept in node order (appended scan by scan; subsets, compaction
        # and adopted maps' -1 keep it): the window is a slice, found in log time (a mask
        # over a long run's 400 000 contributions took ~1.5 ms a try)
        c_node = self.map.c_node
        lo, hi = max(j - window, 0), min(j + window, last)
        if span is not None:
            lo, hi = min(lo, span[0]), max(hi, span[1])
        if nodes is not None:
            sel = np.isin(c_node, nodes)
            r = np.isin(self._retired[0], nodes)
        else:
            sel = _node_slice(c_node, lo, hi)
            r = _node_slice(self._retired[0], lo, hi)
        nodes, ca, cb = c_node[sel], self.map.c_a[sel], self.map.c_b[sel]
        rn, ra, rb = self._retired
        if len(rn[r]):
            nodes = np.concatenate([nodes, rn[r]])
            ca, cb = np.concatenate([ca, ra[r]]), np.concatenate([cb, rb[r]])
        if len(nodes) < 3:
            return None
        rel = relative(X[j], X[nodes])
        c, s = np.cos(rel[:, 2]), np.sin(rel[:, 2])
        R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
        return LineMap(np.einsum("kij,kj->ki", R, ca) + rel[:, :2],
                       np.einsum("kij,kj->ki", R, cb) + rel[:, :2])

    def _guess_rivals(self, seg: Segments, sub: LineMap, guess: np.ndarray, corr: Correction,
                      LP: LoopParams, travel: float) -> bool:
        """Whether the pose the mapper already has, refined against the submap as the
        relocalised one was, is the better one: elsewhere, and matching more of the scan.  A small
        submap (an earlier visit's few scans) may cover only part of what the scan sees; a
        pose slid along its longest wall can then put more points on it than the true one,
        and the point score alone would make a jump of metres out of odometry that was right."""
        if LP.guess_margin is None:
            return False
        here = correct_pose(seg, sub.a, sub.b, guess, 1.0, self.params.correction)
        apart = float(np.hypot(*relative(here.pose, corr.pose)[:2]))
        if apart <= 0.3:
            return False  # the same place
        lead = corr.matched_fraction - here.matched_fraction
        if lead < -LP.guess_margin:
            return True
        a, b = LP.tie_jump
        return bool(lead <= LP.guess_margin and apart > a + b * travel)

    def _closure_by_tracking(self, seg: Segments, sub: LineMap, guess: np.ndarray):
        """The cheap way first: point-to-line correction from the current estimate with wide
        gates; accepted when it fixes the pose in every direction and the scan fits."""
        LP = self.params.loop
        corr = correct_pose(seg, sub.a, sub.b, guess, 4.0, LP.tracking)
        std = np.sqrt(np.linalg.eigvalsh(corr.cov[:2, :2]).max())
        if std > LP.max_std or corr.matched_fraction < 0.5:
            return None
        sc = inlier_fraction(seg.points, corr.pose, sub.a, sub.b, self.params.reloc.inlier_dist)
        if sc < LP.tracking_score:
            return None
        return Hypothesis(corr.pose, sc)

    def optimize(self, final: bool = False) -> None:
        """Solve the pose graph and move the map with it (while mapping: the window of
        :class:`LoopParams` ``online_window``, without the nodes an adopted finishing pass
        placed, ``finished_upto``; ``final``: all nodes)."""
        LP = self.params.loop
        start = 0 if final else max(0, self.count - LP.online_window, self.finished_upto)
        # the whole-graph solve too: map build's final solve on Intel re-trusted two wrong
        # closures and ended 10 iterations later still 0.6 mm a step from converged
        self.graph.optimize(fixed=self.anchors, free_from=start, judged=self._judged)
        self._judged = len(self.graph.ei)
        refresh(self.map, self.poses)
        # the walls near the closure are the ones that came to coincide
        dedupe(self.map, self.params.map, since=None if final else self.count - 60)
        self.pending = False
        self.last_opt = self.count - 1
        self.optimizations += 1

    def finish(self) -> np.ndarray:
        """Final optimisation of all nodes (if loops were closed), then the finishing pass
        (:class:`FinishJob`: tracking sweep, neighbour rounds, line adjustment), the same
        computation the daemon runs on a snapshot; returns the laser poses."""
        if self.params.loop.enabled and self.loops:
            self.optimize(final=True)
        self.apply_finish(self._job(None, sweep=True).run())
        return self.poses

    def neighbour_pairs(self, NP: NeighbourParams | None = None) -> np.ndarray:
        """(p, 2) node pairs j < i for the neighbour pass: positions within ``radius`` in the
        current estimate, and each node with its ``previous`` predecessors."""
        return neighbour_pairs(self.poses, self.scans, NP or self.params.neighbours)

    def finishing_job(self, NP: NeighbourParams | None = None,
                      sweep: bool = False) -> FinishJob:
        """The finishing pass on a copy of the graph and the kept scans, to be computed
        anywhere (:meth:`FinishJob.run` touches nothing of this mapper) and applied with
        :meth:`apply_finish` -- :meth:`finish` does both; a mapper that never finishes (the
        daemon) gets the pass this way without stopping its scans (``max_pairs`` keeps it
        linear in the nodes however long the robot runs).  ``sweep`` adds the tracking
        closures (:func:`sweep_matches`) before the neighbour rounds."""
        if len(self.scans) != self.count:
            raise ValueError("this mapper keeps no per-scan segments (keep_scans)")
        return self._job(NP, sweep)

    def live_finishing_job(self) -> FinishJob:
        """:meth:`finishing_job` as a mapper that keeps mapping takes it (the daemon's
        ``optimize``): the pass's parameters enabled whatever the mapping ones say, with the
        tracking sweep (``NeighbourParams.max_pairs`` bounds each node's spatial pairs:
        months of passes through one room must not make them quadratic)."""
        return self.finishing_job(replace(self.params.neighbours, enabled=True), sweep=True)

    def _job(self, NP: NeighbourParams | None, sweep: bool) -> FinishJob:
        """:meth:`finishing_job`; without kept scans (``keep_scans`` off) a job of the line
        adjustment alone."""
        g = self.graph
        kept = len(self.scans) == self.count
        copy = g.copy()
        LP, AP = self.params.loop, self.params.adjust
        do_sweep = kept and sweep and LP.enabled and LP.sweep_every > 0
        NP = NP or self.params.neighbours
        return FinishJob(NP if NP.enabled and kept else replace(NP, rounds=0), copy,
                         list(self.scans) if kept else [],
                         list(self.anchors), self.dropped, self._neighbour_block,
                         self._weighted, LP if do_sweep else None,
                         np.array(self.travel, float), source=self,
                         steps=self.odo_step.array()[:, :5].copy(),
                         shares=prediction_shares(self.odo_cov.array(), self.params.correction,
                                                  self.odo_step[:, 5], self.odo_step[:, 6]),
                         lines=Contributions.of(self.map) if AP.enabled else None,
                         adjust=AP if AP.enabled else None)

    def apply_finish(self, job: FinishJob) -> dict:
        """Adopt a computed :class:`FinishJob`: its edges (if it found any) replace the
        previous pass's, its poses replace the snapshot's nodes (nodes added since follow
        the newest snapshot node rigidly, up to a re-anchor), and the map is rebuilt from
        them.  Nodes compacted away meanwhile drop out with their edges.  Returns figures
        (edges, nodes, max_shift_m); ValueError for another mapper's job (e.g. this one was
        replaced meanwhile)."""
        if job.source is not self:
            raise ValueError("the job is another mapper's snapshot; nothing applied")
        out = {"edges": 0, "nodes": self.count, "max_shift_m": 0.0}
        if job.poses is None:
            return out
        cut = self.dropped - job.base     # nodes compacted away since the snapshot
        n_snap = len(job.poses)
        old = self.poses
        new = old.copy()
        k = np.arange(max(cut, 0), n_snap)
        new[k - cut] = job.poses[k]
        ref = n_snap - 1 - cut             # the newest snapshot node, live numbering
        later = [a for a in self.anchors if a > ref]
        stop = min(later) if later else self.count
        if ref >= 0 and stop > ref + 1:
            # the scans mapped while the job ran: moved with the chain they hang on
            new[ref + 1:stop] = compose(new[ref], relative(old[ref], old[ref + 1:stop]))
        E = job.edges
        keep = E.i - cut >= 0
        edges = EdgeArrays(E.i[keep] - cut, E.j[keep] - cut, E.z[keep], E.info[keep],
                           E.robust[keep])
        self.graph.poses = new
        if len(edges):
            self._neighbour_block, self._weighted = replace_neighbour_edges(
                self.graph, self._neighbour_block, self._weighted, edges, job.params)
            self.neighbour_edges = len(edges)
        self.sweep_edges = job.sweep_edges
        self.round_moves = list(job.round_moves)
        if job.adjusted:
            self.adjusted = job.adjusted
        if job.calibration:
            # the whole run's estimate predicts the next scans better than the online one
            self.calibration = job.calibration
            self.scale = job.calibration["scale"]
            self.drift_per_m = job.calibration["drift_per_m"]
        # the snapshot's nodes stay where the pass put them; the ones mapped meanwhile only
        # followed it
        self.finished_upto = max(ref + 1, 0)
        self._judged = len(self.graph.ei)
        refresh(self.map, new)
        dedupe(self.map, self.params.map)
        self.optimizations += 1
        shift = float(np.hypot(*(new[:, :2] - old[:, :2]).T).max()) if len(new) else 0.0
        return {"edges": len(edges), "nodes": self.count, "max_shift_m": shift}


def prediction_shares(cov: np.ndarray, params: CorrectionParams, step: np.ndarray,
                      heading: np.ndarray) -> np.ndarray:
    """How much of a change in its prediction each corrected pose would have followed, in
    the frame of the pose it was predicted from (k, 3, 3): the posterior covariance ``cov``
    (k, 3, 3, global frame) times the odometry prior's information after ``step`` metres,
    (I - K) of a Kalman update.  Along a corridor ~1 (the pose is the prediction), across it
    ~0 (the walls placed it); the prior's own covariance gives I, a zero one 0."""
    share = cov * params.prior_information(step)[:, None, :]  # cov @ diag(information)
    c, s = np.cos(heading), np.sin(heading)
    R = np.zeros((len(c), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return np.einsum("kba,kbc,kcd->kad", R, share, R)


def scan_poses(nodes: np.ndarray, node: np.ndarray, offset: np.ndarray,
               online: np.ndarray) -> np.ndarray:
    """Each scan's final pose: its graph node's (``nodes`` indexed by ``node``), moved by
    its ``offset`` from that node when it was only tracked; a scan whose node is gone
    (compacted) keeps its ``online`` pose."""
    out = np.array(online, dtype=float)
    ok = (node >= 0) & (node < len(nodes))
    out[ok] = compose(nodes[node[ok]], offset[ok])
    return out


def _node_slice(nodes: np.ndarray, lo: int, hi: int) -> slice:
    """The rows of node-sorted ``nodes`` whose node lies in [lo, hi]."""
    return slice(int(np.searchsorted(nodes, lo, side="left")),
                 int(np.searchsorted(nodes, hi, side="right")))
