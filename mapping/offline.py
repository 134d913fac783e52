"""Offline runs over recorded scans: build a map from a log, relocalisation trials.

Pure functions over arrays the caller has read (``mapping`` never reads devices or logs):
scans are objects with ``ranges``, ``angle_min``, ``angle_increment``, ``stamp_ns`` and
optionally ``pose_ref`` (the laser's pose) and ``pose_odom`` (the robot's odometry pose).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .evaluation import (
    align_rigid_2d,
    apply_pose,
    ate,
    icp_agreement,
    odometry_model,
    reference_check,
    revisit_pairs,
    rpe,
    wall_squareness,
)
from .finishing import calibration_figures
from .jit import warm_up
from .linemap import LineMap
from .odometry import (
    add_odometry_noise,
    compose_pose2d,
    integrate_increments,
    laser_mount,
    relative,
    wrap_angle,
)
from .relocalize import DistanceField, RelocParams, relocalize
from .segments import SegmentParams, extract_segments
from .slam2d import Mapper, MapperParams, scan_poses


@dataclass
class BuildResult:
    map: LineMap
    poses: np.ndarray        # (n, 3) estimated laser poses (after the final optimisation)
    stamps: np.ndarray       # (n,) seconds
    report: dict
    node_scan: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # per graph node,
    # the scan it was (the others were tracked from the node before them)


def _stats_ms(ts) -> tuple[float, float]:
    ms = np.asarray(ts) * 1e3
    return (float(np.median(ms)), float(np.percentile(ms, 95))) if len(ms) else (0.0, 0.0)


WHEELS = "wheels"  # the odometry choice that replays a log's own ODOM readings


def log_odometry(scans: Sequence, preset: str = "none", seed: int = 0,
                 wheels: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """The laser's odometry (n, 3) for replaying a log, and the laser's mount (None for a
    laser at the robot's centre).  Each scan's odometry pose (its reference pose where it
    has none) gets ``preset`` noise on the robot's increments (:func:`.add_odometry_noise`),
    then is carried to the laser by the one offset the log's laser poses keep from it
    (:func:`.laser_mount`): a laser off the centre moves differently when the robot turns.
    With ``preset`` ``"wheels"`` the robot's steps are instead the log's own wheel odometry
    between the scans, ``wheels`` = (at, start) as :func:`wheel_steps` takes them, chained
    from the first scan's odometry pose, with no noise added.
    ValueError when a scan carries no pose at all, or ``wheels`` is missing or unusable."""
    odo = [s.pose_odom if s.pose_odom is not None else s.pose_ref for s in scans]
    if any(o is None for o in odo):
        raise ValueError("scans carry no poses (no odometry fields)")
    odo = np.array(odo, dtype=float).reshape(-1, 3)
    ref = [s.pose_ref for s in scans]
    mount = (laser_mount(odo, np.array(ref, float)) if all(r is not None for r in ref)
             and all(s.pose_odom is not None for s in scans) else None)
    if preset == WHEELS:
        if wheels is None:
            raise ValueError("the log has no ODOM lines (wheel odometry) to replay")
        steps, unknown = wheel_steps(*wheels)
        if len(steps) and unknown == len(steps):
            raise ValueError("no ODOM reading falls between two scans")
        odo = integrate_increments(steps, odo[0]) if len(odo) else odo
    else:
        odo = add_odometry_noise(odo, preset, seed)
    return (odo if mount is None else compose_pose2d(odo, mount)), mount


def wheel_steps(at: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, int]:
    """The robot's (n - 1, 3) steps between n scans from its wheel odometry: step k from
    ``start[k]`` to ``at[k + 1]`` (a log's readings at each scan, and where the readings
    after it count from; the same poses in a log of raw odometry), and how many were
    unknown (a NaN reading) and taken as no motion."""
    at, start = np.asarray(at, float).reshape(-1, 3), np.asarray(start, float).reshape(-1, 3)
    steps = relative(start[:-1], at[1:])
    unknown = ~np.isfinite(steps).all(axis=1)
    steps[unknown] = 0.0
    return steps, int(unknown.sum())


def build_map(scans: Sequence, odometry: np.ndarray, params: MapperParams | None = None,
              progress: Callable[[int, int], None] | None = None,
              status: Callable[[str], None] | None = None) -> BuildResult:
    """Run the mapper over ``scans`` with odometry poses (n, 3); score against the scans'
    ``pose_ref`` when every scan has one.  ``progress(k, n)`` after each scan; ``status``
    gets a line as each later stage starts and ends (on a long log the finishing pass and
    the scoring take minutes, with no scan count to show)."""
    say = status or (lambda line: None)
    say(f"mapper kernels ready in {warm_up():.1f} s")  # compiled before the timing starts
    odometry = np.asarray(odometry, dtype=float)
    mapper = Mapper(params, initial_pose=odometry[0] if len(odometry) else (0, 0, 0))
    times = []
    n = len(scans)
    online = np.zeros((n, 3))
    node = np.zeros(n, dtype=int)      # each scan's graph node, or the node it was tracked
    offset = np.zeros((n, 3))          # from, and its pose relative to that node
    t_all = time.perf_counter()
    for k, (scan, odo) in enumerate(zip(scans, odometry, strict=True)):
        t = time.perf_counter()
        res = mapper.step(scan.ranges, scan.angle_min, scan.angle_increment, odo)
        times.append(time.perf_counter() - t)
        online[k], node[k], offset[k] = res.pose, res.node, res.offset
        if progress is not None:
            progress(k + 1, n)
    t = time.perf_counter()
    say(f"finishing pass over {mapper.count} graph nodes of the {n} scans "
        "(neighbour matching, graph, walls) ...")
    poses = scan_poses(mapper.finish(), node - mapper.dropped, offset, online)
    # the scans tracked between nodes: matched again, on the finished map
    for k in np.flatnonzero(np.any(offset != 0.0, axis=1)):
        poses[k] = mapper.place(scans[k].ranges, scans[k].angle_min, scans[k].angle_increment,
                                poses[k])
    t_final = time.perf_counter() - t
    say(f"finishing pass done in {t_final:.1f} s")
    med, p95 = _stats_ms(times)
    report = {
        "scans_processed": n,
        # scans that became graph nodes (the others were tracked from them:
        # MapperParams.node_travel, node_turn)
        "graph_nodes": mapper.count,
        "segments": len(mapper.map),
        "ms_per_scan_median": round(med, 3),
        "ms_per_scan_p95": round(p95, 3),
        "final_optimisation_ms": round(t_final * 1e3, 1),
        "total_s": round(time.perf_counter() - t_all, 2),
        "loop_closures": mapper.loops,
        # what became of the online closure attempts (tracked: taken by the cheap tracking
        # correction; tried: relocalised in a submap, then refused by the reason counted)
        "closure_attempts": dict(mapper.loop_stats),
        "sweep_closures": mapper.sweep_edges,
        # the finishing pass's neighbour rounds: how far each moved the map (RMS, after a
        # rigid alignment); it stops once one moves it less than NeighbourParams.converged
        "neighbour_round_moves_m": mapper.round_moves,
        "slips_recovered": mapper.slips,
        # map segments later scans saw through (people, carts, doors that moved on)
        "segments_cleared": mapper.cleared,
        # scan segments not mapped: where a scan a moment earlier saw through (on the move)
        "segments_moving": mapper.moved,
        "optimisations": mapper.optimizations,
        "line_adjustment": mapper.adjusted,
    }
    if mapper.calibration:
        report["odometry_calibration"] = calibration_figures(mapper.calibration)
    ref = [getattr(s, "pose_ref", None) for s in scans]
    R = None
    if n >= 2 and all(r is not None for r in ref):
        say("scoring against the log's reference poses (ATE, RPE, ICP agreement) ...")
        R = np.array(ref, dtype=float)
        report.update({k: round(v, 4) if isinstance(v, float) else v
                       for k, v in {**ate(poses, R), **rpe(poses, R)}.items()})
        # the map's frame is the log's first pose; this rigid motion takes it onto the
        # reference frame (the gauge of the ATE), for scoring relocalisation against it
        report["alignment_to_reference"] = [round(v, 6) for v in align_rigid_2d(poses, R)]
        odo = {**ate(odometry, R), **rpe(odometry, R)}
        report["odometry"] = {k: round(v, 4) if isinstance(v, float) else v
                              for k, v in odo.items()}
        # the odometry's error in the calibration's terms (what odometry_calibration
        # estimated without the reference)
        report["odometry"]["model"] = odometry_model(odometry, R)
        # each scan's pose as the mapper gave it when the scan came in (what a daemon serves
        # the robot): later closures and the finishing pass have not corrected it yet
        report["online"] = {k: round(v, 4) for k, v in ate(online, R).items()}
        # a log's reference is usually another SLAM run, not ground truth: how closely the
        # estimate and the reference each follow raw-point ICP between consecutive scans
        # says which of the two the ATE's disagreement is more likely to come from
        report["icp_agreement"] = icp_agreement(scans, {"estimate": poses, "reference": R}, R)
    if n >= 2:
        # with or without reference poses: how square the walls come out along the estimate,
        # the odometry and (when the log has one) the reference
        say("scoring the walls' squareness ...")
        tracks = {"estimate": poses, "odometry": odometry}
        if R is not None:
            tracks["reference"] = R
        report["squareness"] = squareness(scans, tracks, mapper.params.segments)
        check = reference_check(report["squareness"])
        if check is not None:
            report["reference_check"] = check
    stamps = np.array([s.stamp_ns for s in scans], dtype=float) * 1e-9
    return BuildResult(mapper.map, poses, stamps, report, mapper.node_scan.array().copy())


def squareness(scans: Sequence, trajectories: dict, params: SegmentParams | None = None
               ) -> dict:
    """:func:`.evaluation.wall_squareness` of each trajectory (n, 3) over the scans' walls."""
    walls = []
    for s in scans:
        seg = extract_segments(s.ranges, s.angle_min, s.angle_increment, params)
        walls.append((seg.a, seg.b))
    return {name: wall_squareness(walls, np.asarray(X, float))
            for name, X in trajectories.items()}


def revisit_agreement(scans: Sequence, poses: np.ndarray, max_pairs: int = 1000) -> dict:
    """Raw-point ICP agreement (:func:`.evaluation.icp_agreement`) of the estimate ``poses``
    and, when the scans carry them, the reference poses, at the revisits: the pairs of
    :func:`.evaluation.revisit_pairs` (by the reference, else by the estimate), where a loop
    closed wrong or loosely shows."""
    ref = [getattr(s, "pose_ref", None) for s in scans]
    tracks = {"estimate": np.asarray(poses, float)}
    if all(r is not None for r in ref):
        tracks["reference"] = np.array(ref, dtype=float)
    guide = tracks.get("reference", tracks["estimate"])
    pairs = revisit_pairs(guide)
    return {"revisit_pairs": int(len(pairs)),
            **icp_agreement(scans, tracks, guide, max_pairs=max_pairs, pairs=pairs)}


def relocalize_trials(lmap: LineMap, scans: Sequence, trials: int, seed: int = 0,
                      params: RelocParams | None = None,
                      segment_params: SegmentParams | None = None,
                      truth: np.ndarray | None = None,
                      max_trans: float = 0.2, max_rot_deg: float = 3.0,
                      alignment=None,
                      progress: Callable[[int, int], None] | None = None,
                      also: dict | None = None) -> dict:
    """Relocalise ``trials`` scans drawn at random (seeded) with their poses hidden; success
    when within ``max_trans`` and ``max_rot_deg`` of ``truth`` (default: scans' pose_ref).
    ``alignment`` (x, y, theta) first moves map-frame poses into the truth's frame.
    ``also``: {name: (n, 3) poses in the map's own frame}, the same answers scored against
    each as well (success figures under that name): a map built by another run sits off
    the reference by its ATE, and against the build's own trajectory that is left out."""
    rng = np.random.default_rng(seed)
    n = len(scans)
    if truth is None:
        truth = np.array([s.pose_ref for s in scans], dtype=float)
    idx = rng.choice(n, size=trials, replace=trials > n)
    warm_up()  # a first trial must not time the kernels' compilation
    t0 = time.perf_counter()
    P = params or RelocParams()
    field = DistanceField(lmap, P.field_resolution)
    if P.point_refine:
        field.seg_id  # noqa: B018  (built once here, counted with the field, not a trial)
    field_ms = (time.perf_counter() - t0) * 1e3
    times, cpu, answers = [], [], []
    for k, i in enumerate(idx):
        s = scans[int(i)]
        t, tc = time.perf_counter(), time.process_time()
        seg = extract_segments(s.ranges, s.angle_min, s.angle_increment, segment_params)
        res = relocalize(lmap, seg, field, params)
        times.append(time.perf_counter() - t)
        # CPU time too: on a shared machine the wall clock also counts other processes
        cpu.append(time.process_time() - tc)
        answers.append(np.array([h.pose for h in res.hypotheses[:3]]).reshape(-1, 3)
                       if res.found else None)
        if progress is not None:
            progress(k + 1, trials)
    med, p95 = _stats_ms(times)
    return {
        "trials": int(trials),
        **_trial_successes(answers, truth[idx], trials, max_trans, max_rot_deg, alignment),
        "found": sum(a is not None for a in answers),
        "median_ms": round(med, 2),
        "p95_ms": round(p95, 2),
        "median_cpu_ms": round(_stats_ms(cpu)[0], 2),
        "p95_cpu_ms": round(_stats_ms(cpu)[1], 2),
        "distance_field_ms": round(field_ms, 1),
        "seed": seed,
        "aligned_to_reference": alignment is not None,
        **{name: _trial_successes(answers, np.asarray(poses, float)[idx], trials, max_trans,
                                  max_rot_deg, None)
           for name, poses in (also or {}).items()},
    }


def _trial_successes(answers: list, truth: np.ndarray, trials: int, max_trans: float,
                     max_rot_deg: float, alignment) -> dict:
    """Success figures of relocalisation answers (each trial's best three poses in the map
    frame, or None) against the trials' true poses (moved by ``alignment`` first)."""
    errs_t, errs_r, in_top = [], [], 0
    for ranked, want in zip(answers, truth, strict=True):
        if ranked is None:
            continue
        if alignment is not None:
            ranked = apply_pose(alignment, ranked)
        d = ranked - want
        et = np.hypot(d[:, 0], d[:, 1])
        er = np.degrees(np.abs(wrap_angle(d[:, 2])))
        ok = (et <= max_trans) & (er <= max_rot_deg)
        in_top += bool(ok.any())
        if ok[0]:
            errs_t.append(float(et[0]))
            errs_r.append(float(er[0]))
    succ = len(errs_t)
    return {
        "successes": succ,
        "success_rate": round(succ / trials, 4) if trials else 0.0,
        # the right pose among the first 3 hypotheses: in a symmetric place (a ring of
        # like corridors) the best one alone cannot know which of them it is
        "top3_rate": round(in_top / trials, 4) if trials else 0.0,
        "success_error_trans_m": round(float(np.sqrt(np.mean(np.square(errs_t)))), 4)
        if succ else None,
        "success_error_rot_deg": round(float(np.sqrt(np.mean(np.square(errs_r)))), 3)
        if succ else None,
    }
