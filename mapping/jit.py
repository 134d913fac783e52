"""Compiled kernels for the per-scan hot path (numba).

A scan's correction and segment extraction work on a few dozen segments: in numpy every
step is a call over arrays of tens of elements, and the calls, not the arithmetic, were
the cost (about 2 ms per Intel scan on the 2-core machine, most of it call overhead).  The
few loops that carry that work are compiled; everything else stays numpy.  Relocalisation
compiles its candidate counts, sweeps and verification for the opposite reason: many
thousand candidates, whose (candidates x points) temporaries cost more than the reads.
This module holds the decorator (:func:`kernel`), the one sort and the 3 x 3 inverse the
kernels share (:func:`stable_argsort`, :func:`inverse3_into`) and the warm-up that compiles
them all (:func:`warm_up`).

Compiled code is cached on disk next to the module (numba's ``cache=True``), or under
``NUMBA_CACHE_DIR`` when set (the systemd unit points it at the service's cache
directory).  Where neither location is writable the kernels compile in memory at first
use, with a warning, rather than fail.  ``NUMBA_DISABLE_JIT=1`` runs them as plain Python
(for a debugger; slow).
"""

from __future__ import annotations

import warnings

import numba
import numpy as np


def kernel(fn):
    """``fn`` compiled in nopython mode, cached, releasing the GIL (the daemon maps in a
    thread next to its device threads)."""
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError as exc:  # no cache locator: a read-only install, no cache dir
        warnings.warn(f"numba cannot cache {fn.__qualname__} ({exc}); compiling in memory",
                      RuntimeWarning, stacklevel=2)
        return numba.njit(cache=False, nogil=True)(fn)


@kernel
def stable_argsort(x):
    """``np.argsort(x, kind="stable")`` for a 1-D array, in a kernel: a bottom-up merge sort,
    ties in index order and NaNs last as numpy puts them.  numba compiles numpy's own sorts
    in seconds each (2.3 s for an argsort on the 2-core machine), this in a fraction of one."""
    n = x.size
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            i, j, k = lo, mid, lo
            while i < mid and j < hi:
                a, b = x[idx[i]], x[idx[j]]
                if b < a or (a != a and b == b):      # b first: smaller, or a is NaN and b not
                    tmp[k] = idx[j]
                    j += 1
                else:
                    tmp[k] = idx[i]
                    i += 1
                k += 1
            while i < mid:
                tmp[k] = idx[i]
                i += 1
                k += 1
            while j < hi:
                tmp[k] = idx[j]
                j += 1
                k += 1
        idx, tmp = tmp, idx
        width *= 2
    return idx


@kernel
def inverse3_into(H, out):
    """Inverses of symmetric (P, 3, 3) matrices into ``out`` (which may be ``H``), by
    cofactors: a kernel's 3 x 3 solve without compiling numpy's linear algebra."""
    for p in range(H.shape[0]):
        a, b, c = H[p, 0, 0], H[p, 0, 1], H[p, 0, 2]
        d, e, f = H[p, 1, 1], H[p, 1, 2], H[p, 2, 2]
        A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
        D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
        det = a * A + b * B + c * C
        out[p, 0, 0], out[p, 0, 1], out[p, 0, 2] = A / det, B / det, C / det
        out[p, 1, 0], out[p, 1, 1], out[p, 1, 2] = B / det, D / det, E / det
        out[p, 2, 0], out[p, 2, 1], out[p, 2, 2] = C / det, E / det, F / det


def warm_up() -> float:
    """Compile every kernel for the argument types the mapper passes (or load them from the
    cache), on a tiny made-up scan; returns the seconds it took.  Without a cache that is
    about 25-30 s on the 2-core machine (25-28 s measured on 2026-12-02; 31 s before that
    day's relocalisation kernels, 35-43 s with them before the kernels' sorts were written
    out, :func:`stable_argsort`): the daemon does it before it reports ready (asking systemd for
    the time), not on its first scan."""
    import time

    import numpy as np

    from .correction import correct_pose
    from .linemap import LineMap, dedupe, integrate
    from .segments import extract_segments, tls_from_moments

    t0 = time.perf_counter()
    beams = np.linspace(-np.pi / 2, np.pi / 2, 61)
    # a corner 2 m ahead and 1.5 m to the left: two walls, split, merged, fused
    ranges = np.minimum(2.0 / np.maximum(np.cos(beams), 1e-9),
                        1.5 / np.maximum(np.sin(beams), 1e-9))
    seg = extract_segments(ranges, float(beams[0]), float(beams[1] - beams[0]))
    lmap = LineMap()
    integrate(lmap, seg, 0, seg_l=seg, node=0)
    integrate(lmap, seg, 1, seg_l=seg, node=1)
    dedupe(lmap)
    correct_pose(seg, lmap.a, lmap.b, np.array([0.02, -0.01, 0.01]), 0.1)
    tls_from_moments(seg.n, seg.centroid, seg.scatter)
    from .free_space import update_streaks

    update_streaks(lmap, np.zeros(2), seg.points, 2, beam_step=float(beams[1] - beams[0]))
    from .moving import moved_segments

    moved_segments(seg.a, seg.b, (0.0, 0.0, 0.0), ranges, float(beams[0]),
                   float(beams[1] - beams[0]))
    # relocalisation's line-pair solve and hypothesis score (a trial or the daemon's first
    # relocalisation must not pay for their compilation)
    from .line_hypotheses import line_candidates
    from .pose_verify import best_distinct, crossed_fractions, icp_poses, inlier_scores
    from .relocalize import DistanceField, RelocParams
    from .sweep import branch_and_bound
    one = np.ones((1, 2))
    line_candidates(one, 2 * one, one, *(np.ones(1),) * 3, one, 2 * one, one,
                    *(np.ones(1),) * 3, 1.0, 0.05, 0.5, 0.3, 0.5, 1)
    field = DistanceField(lmap, 0.05)
    for soft in (False, True):
        inlier_scores(field, seg.points, np.zeros((1, 2)), np.zeros(1), 0.2, soft)
    best_distinct(field, seg.points, np.zeros((2, 2)), np.zeros(2), 0.2, 0.3, 0.05, 1)
    icp_poses(field, seg.points, np.zeros((1, 3)), (0.5,))
    crossed_fractions(field, seg.points, np.zeros((1, 3)), RelocParams())
    # a big map's coarse-to-fine sweep
    idx = np.zeros((1, 1), np.int64)
    branch_and_bound(np.ones((1, 1, 1), np.int32), np.ones((1, 2, 2), np.uint8), idx, idx,
                     idx, np.ones((1, 1), bool), 1, 1, np.zeros(1, np.uint16), 0, 0, 1,
                     np.zeros((3, 1, 1), np.int64))
    # the finishing pass's turn from the walls' directions
    from .finishing import pair_turns

    pair_turns(one[None], 2 * one[None], one[None], 2 * one[None], np.zeros(1), 0.1)
    return time.perf_counter() - t0
