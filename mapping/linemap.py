"""The global 2D line map: segments with accumulated fit moments and observation counts.

Merging (issue 4, step 3): an observed segment that matches map segments (eq. 15 sphere test
+ angle + end-point distance, :mod:`.matching`) is fused with them: point counts, centroids
and scatter matrices add (parallel-axis rule), the line is refitted by total least squares
and its extent is the union of the projected extents.  Unmatched observations become new
segments.  Short segments seen only once are aged out, and map segments that came to
coincide (the same wall seen twice before the pose was pulled back) are fused periodically,
so duplicate walls do not pile up.  Segments the laser now sees through (a parked cart
moved on, a door opened) are dropped too (:mod:`.free_space`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .free_space import ClearParams
from .jit import kernel, stable_argsort
from .matching import match_candidates
from .segments import Segments, tls_fit


@dataclass(frozen=True)
class MapParams:
    merge_angle: float = np.deg2rad(5.0)
    merge_dist: float = 0.10       # end points within this of the map line
    merge_margin: float = 0.30     # sphere enlargement: pieces this far apart along a wall join
    age_scans: int = 12            # a segment seen once is judged after this many scans
    age_min_length: float = 0.6    # ... and dropped if shorter than this, ...
    # ... or of any length when the robot went at most this far (odometry, m) in those
    # scans: scanning densely, the next scans looked at it from nearly where it was seen,
    # and a wall they did not see again was something moving (a person's or a cart's side
    # laid down once per scan, 0.5-0.8 m long: a comb of them along its way).  Sparse logs
    # (the Intel lab: 0.6 m or more in 12 scans, 6 m in the median) keep their glimpses
    age_travel: float = 1.0
    # ... and so is one seen at most this many times in those scans and never after: a
    # wall is seen by nearly every one of them (the copies of a side fused in twos and
    # threes; in the empty hall at 10 Hz, fragments of walls seen better by others)
    age_seen: int = 3
    # ... unless the robot also turned more than this (rad, odometry) in those scans: a
    # turn on the spot takes what it saw at one side out of view (Intel's sparse scans
    # turn 0.3-0.5 rad each there)
    age_turn: float = 0.5
    # judged every this many scans: each drop re-indexes every contribution (thousands of
    # rows), and with 15 cm segments some short piece goes nearly every scan.  Intel seeds
    # 0-3: 0.064 -> 0.061 m mean ATE, the scans' median time down by about a tenth
    age_every: int = 4
    # ... and at most once per this many contribution rows, in scans: a drop copies every
    # row (the dropped segments' contributions go), and a long run holds hundreds of
    # thousands (the Intel log driven 20 times: 3.3 ms per scan at 174 000 rows, most of it
    # those copies).  Spread so, the copies cost a bounded share of each scan
    age_rows: int = 10_000
    dedupe_every: int = 10
    dedupe_margin: float = 0.05    # sphere enlargement when fusing map segments with each other
    # a fusion must still be one line: two sets of observations join when the joint line
    # adds to their squared residuals no more than this RMS offset over the smaller set's
    # points (:func:`fusions`).  Not the joint residual itself: a wall seen from many poses
    # is a few cm thick, and a test on its thickness refused every later observation of it,
    # so revisits laid copies beside it (the Intel log driven four times, there and back,
    # with its reference poses as odometry: 798 -> 1 327 segments after the finishing pass,
    # 692 of them with a copy within 3 cm; now 776 -> 789, 3)
    max_residual: float = 0.03
    # segments the laser now sees through go (:mod:`.free_space`), judged with the aging
    clear: ClearParams = field(default_factory=ClearParams)


@dataclass
class LineMap:
    """m segments: end points, moments of all fused points, counts, bookkeeping."""

    a: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    b: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    n_pts: np.ndarray = field(default_factory=lambda: np.zeros(0))
    centroid: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    scatter: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    n_obs: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    created: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    last_seen: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    metadata: dict = field(default_factory=dict)
    # contributions: which scan (node) saw which segment, with the observation's moments and
    # end points in that scan's laser frame, so the map can follow re-optimised poses
    c_seg: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    c_node: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    c_n: np.ndarray = field(default_factory=lambda: np.zeros(0))
    c_cent: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    c_scat: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    c_a: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    c_b: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    # per segment: scans in a row that saw through it (:mod:`.free_space`); not saved in
    # map files (evidence of the current run)
    through: np.ndarray = field(default_factory=lambda: np.zeros(0, int))

    def __post_init__(self) -> None:
        if len(self.through) != len(self.a):  # built from end points, or an older state
            self.through = np.zeros(len(self.a), int)

    def __len__(self) -> int:
        return len(self.a)

    @property
    def length(self) -> np.ndarray:
        return np.linalg.norm(self.b - self.a, axis=-1)

    def subset(self, keep) -> LineMap:
        """The segments selected by boolean ``keep`` (contributions follow; when none of
        them goes, the result shares this map's contribution arrays)."""
        keep = np.asarray(keep, bool)
        remap = np.where(keep, np.cumsum(keep) - 1, -1)
        out = self._rows(keep)
        if len(self.c_seg):
            new = remap[self.c_seg]
            ok = new >= 0
            if ok.all():
                # no contribution goes (they were redirected to the segments kept): the
                # contribution rows are shared, not copied -- thousands of them, re-indexed
                # whenever a scan fuses two map segments into one
                out.c_seg, out.c_node, out.c_n = new, self.c_node, self.c_n
                out.c_cent, out.c_scat, out.c_a, out.c_b = (self.c_cent, self.c_scat,
                                                            self.c_a, self.c_b)
            else:
                out.c_seg, out.c_node, out.c_n = new[ok], self.c_node[ok], self.c_n[ok]
                out.c_cent, out.c_scat = self.c_cent[ok], self.c_scat[ok]
                out.c_a, out.c_b = self.c_a[ok], self.c_b[ok]
        return out

    def _rows(self, keep: np.ndarray) -> LineMap:
        """The segments selected by boolean ``keep``, sharing this map's contribution rows
        as they are (the caller renumbers or drops them).  Fields set directly: the
        constructor's empty contribution columns would be made only to be replaced."""
        out = object.__new__(LineMap)
        out.__dict__.update(
            a=self.a[keep], b=self.b[keep], n_pts=self.n_pts[keep],
            centroid=self.centroid[keep], scatter=self.scatter[keep], n_obs=self.n_obs[keep],
            created=self.created[keep], last_seen=self.last_seen[keep],
            metadata=dict(self.metadata), through=self.through[keep],
            c_seg=self.c_seg, c_node=self.c_node, c_n=self.c_n, c_cent=self.c_cent,
            c_scat=self.c_scat, c_a=self.c_a, c_b=self.c_b)
        return out

    def add_contributions(self, target: np.ndarray, node: int, seg_l: Segments) -> None:
        k = len(target)
        for name, rows in (("c_seg", target), ("c_node", np.full(k, node)),
                           ("c_n", seg_l.n), ("c_cent", seg_l.centroid),
                           ("c_scat", seg_l.scatter), ("c_a", seg_l.a), ("c_b", seg_l.b)):
            setattr(self, name, self._appended(name, rows))

    def _appended(self, name: str, rows: np.ndarray) -> np.ndarray:
        """Contribution column ``name`` with ``rows`` after it.  The columns are prefixes of
        buffers with room to grow (every scan adds a few rows to tens of thousands, and a
        copy each time made a long run's steps slower the longer it ran).  Rows are written
        in place only when the column is the very view this returned last time; any other
        column (a subset, a compaction, a copy of this map) gets a new buffer, so views
        handed out earlier never change."""
        cur = getattr(self, name)
        bufs = self.__dict__.setdefault("_buffers", {})  # not a field: never saved
        buf, last = bufs.get(name, (None, None))
        n, k = len(cur), len(rows)
        if cur is not last or len(buf) < n + k:
            buf = np.empty((max(2 * (n + k), 256), *cur.shape[1:]), cur.dtype)
            buf[:n] = cur
        buf[n:n + k] = rows
        view = buf[:n + k]
        bufs[name] = (buf, view)
        return view

    def append(self, seg: Segments, stamp: int) -> None:
        k = len(seg)
        self.a = np.concatenate([self.a, seg.a])
        self.b = np.concatenate([self.b, seg.b])
        self.n_pts = np.concatenate([self.n_pts, seg.n.astype(float)])
        self.centroid = np.concatenate([self.centroid, seg.centroid])
        self.scatter = np.concatenate([self.scatter, seg.scatter])
        self.n_obs = np.concatenate([self.n_obs, np.ones(k, int)])
        self.created = np.concatenate([self.created, np.full(k, stamp)])
        self.last_seen = np.concatenate([self.last_seen, np.full(k, stamp)])
        self.through = np.concatenate([self.through, np.zeros(k, int)])


_IMAX, _IMIN = np.iinfo(np.int64).max, np.iinfo(np.int64).min


def fuse_groups(group: np.ndarray, m: int, n: np.ndarray, centroid: np.ndarray,
                scatter: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple:
    """Segments fused from their members, many groups at once: members with ``group`` label g
    in [0, m) form segment g (:func:`_fuse_groups`).  Returns per group (count N, centroid
    C, scatter S, end points pa, pb, RMS orthogonal residual); groups without members get
    N = 0 (and meaningless geometry)."""
    f = np.ascontiguousarray
    return _fuse_groups(f(group, dtype=np.int64), int(m), f(n, dtype=float),
                        f(centroid, dtype=float), f(scatter, dtype=float), f(a, dtype=float),
                        f(b, dtype=float))


@kernel
def _fuse_groups(group, m, n, centroid, scatter, a, b):
    """Moments add per group (counts, weighted centroids, scatter by the parallel-axis
    rule), each group's line is their total-least-squares fit and its extent the union of
    its members' end points projected on it."""
    N = np.zeros(m)
    C = np.zeros((m, 2))
    S = np.zeros((m, 2, 2))
    for k in range(len(group)):
        g = group[k]
        N[g] += n[k]
        C[g, 0] += n[k] * centroid[k, 0]
        C[g, 1] += n[k] * centroid[k, 1]
    Nn = np.where(N > 0, N, 1.0)  # an empty group: no division by zero
    for g in range(m):
        C[g, 0] /= Nn[g]
        C[g, 1] /= Nn[g]
    for k in range(len(group)):
        g = group[k]
        dx, dy = centroid[k, 0] - C[g, 0], centroid[k, 1] - C[g, 1]
        S[g, 0, 0] += scatter[k, 0, 0] + n[k] * dx * dx
        S[g, 0, 1] += scatter[k, 0, 1] + n[k] * dx * dy
        S[g, 1, 1] += scatter[k, 1, 1] + n[k] * dy * dy
    d = np.empty((m, 2))
    rms = np.empty(m)
    for g in range(m):
        S[g, 1, 0] = S[g, 0, 1]
        ms, _, d[g, 0], d[g, 1] = tls_fit(Nn[g], S[g, 0, 0], S[g, 0, 1], S[g, 1, 1])
        rms[g] = np.sqrt(ms)
    lo = np.full(m, np.inf)
    hi = np.full(m, -np.inf)
    for k in range(len(group)):
        g = group[k]
        ta = (a[k, 0] - C[g, 0]) * d[g, 0] + (a[k, 1] - C[g, 1]) * d[g, 1]
        tb = (b[k, 0] - C[g, 0]) * d[g, 0] + (b[k, 1] - C[g, 1]) * d[g, 1]
        lo[g] = min(lo[g], ta, tb)
        hi[g] = max(hi[g], ta, tb)
    pa = np.empty((m, 2))
    pb = np.empty((m, 2))
    for g in range(m):
        if N[g] == 0:
            lo[g] = hi[g] = 0.0
        for i in range(2):
            pa[g, i] = C[g, i] + lo[g] * d[g, i]
            pb[g, i] = C[g, i] + hi[g] * d[g, i]
    return N, C, S, pa, pb, rms


def unique_inverse(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(x, return_inverse=True)`` for a short integer array: the same two
    arrays, compiled (numpy's costs ~15 us a call in its own overhead, three calls a scan)."""
    return _unique_inverse(np.ascontiguousarray(x, dtype=np.int64))


@kernel
def _unique_inverse(x):
    order = stable_argsort(x)
    inv = np.empty(len(x), np.int64)
    vals = np.empty(len(x), np.int64)
    n = -1
    for q in range(len(x)):
        i = order[q]
        if n < 0 or x[i] != vals[n]:
            n += 1
            vals[n] = x[i]
        inv[i] = n
    return vals[:n + 1], inv


def fusions(u: np.ndarray, v: np.ndarray, cost: np.ndarray, n: np.ndarray,
            centroid: np.ndarray, scatter: np.ndarray,
            max_offset: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Which of the candidate pairs (u, v) of items (segments, observations; their point
    counts, centroids and scatters indexed by item number) to fuse, as groups (member,
    group, count, as :func:`_components`).  Pairs are taken cheapest first; a pair joins
    its two groups when their joint line adds to their squared residuals no more than
    ``max_offset`` RMS over the smaller group's points (two parallel lines d apart: about
    d, however thick either is).  Along a cluttered wall the candidates chain the wall's
    pieces and the desks beside it into one component that is no line; judged whole, it
    kept every piece apart for good."""
    if not len(u):
        return _components(u, v)
    nodes, inv = unique_inverse(np.concatenate([u, v]))
    order = np.argsort(cost, kind="stable")
    eu, ev = inv[: len(u)][order], inv[len(u):][order]
    ok = _greedy_unions(len(nodes), eu, ev, np.ascontiguousarray(n[nodes], dtype=float),
                        np.ascontiguousarray(centroid[nodes], dtype=float),
                        np.ascontiguousarray(scatter[nodes], dtype=float), float(max_offset))
    return _components(u[order][ok], v[order][ok])


@kernel
def _greedy_unions(nn, eu, ev, n, cent, scat, max_offset):
    """Union-find over edges in order: an edge joins its two sets when what the joint line
    adds to their squared residuals, per point of the smaller set, is within
    ``max_offset`` squared.  Each set carries its count and its moments about its first
    item's centroid."""
    parent = np.arange(nn)
    N = n.copy()
    ox, oy = cent[:, 0].copy(), cent[:, 1].copy()   # reference point of each set
    sx, sy = np.zeros(nn), np.zeros(nn)             # sums of n * (centroid - reference)
    mxx, mxy, myy = scat[:, 0, 0].copy(), scat[:, 0, 1].copy(), scat[:, 1, 1].copy()
    sse = np.empty(nn)                               # each set's own squared residuals
    for i in range(nn):
        sse[i] = tls_fit(N[i], mxx[i], mxy[i], myy[i])[0] * N[i]
    ok = np.zeros(len(eu), np.bool_)
    for q in range(len(eu)):
        a, b = _root(parent, eu[q]), _root(parent, ev[q])
        if a == b:
            continue
        # b's moments about a's reference point
        dx, dy = ox[b] - ox[a], oy[b] - oy[a]
        tx, ty = sx[a] + sx[b] + N[b] * dx, sy[a] + sy[b] + N[b] * dy
        txx = mxx[a] + mxx[b] + 2.0 * dx * sx[b] + N[b] * dx * dx
        txy = mxy[a] + mxy[b] + dx * sy[b] + dy * sx[b] + N[b] * dx * dy
        tyy = myy[a] + myy[b] + 2.0 * dy * sy[b] + N[b] * dy * dy
        Nt = N[a] + N[b]
        joint = tls_fit(Nt, txx - tx * tx / Nt, txy - tx * ty / Nt, tyy - ty * ty / Nt)[0] * Nt
        if joint - sse[a] - sse[b] > max_offset * max_offset * max(min(N[a], N[b]), 1.0):
            continue
        parent[b] = a
        N[a], sx[a], sy[a] = Nt, tx, ty
        mxx[a], mxy[a], myy[a] = txx, txy, tyy
        sse[a] = joint
        ok[q] = True
    return ok


def _components(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Connected components of the graph of edges (u, v) (node numbers), as (member, group,
    count): each component's nodes ascending, the components in the order of their smallest
    node."""
    if not len(u):
        return np.zeros(0, int), np.zeros(0, int), 0
    nodes, inv = unique_inverse(np.concatenate([u, v]))
    order, group, count = _component_order(len(nodes), inv[: len(u)], inv[len(u):])
    return nodes[order], group, count


@kernel
def _component_order(nn, eu, ev):
    """Union-find over nodes 0..nn-1 joined by edges (eu, ev), each root the smallest node
    of its set; returns the nodes grouped by component (ascending within, components by
    their smallest node), their component numbers and the count."""
    parent = np.arange(nn)
    for q in range(len(eu)):
        ra, rb = _root(parent, eu[q]), _root(parent, ev[q])
        if ra < rb:
            parent[rb] = ra
        elif rb < ra:
            parent[ra] = rb
    first = np.full(nn, -1)  # component number, set at each component's smallest node
    size = np.zeros(nn, np.int64)
    count = 0
    lab = np.empty(nn, np.int64)
    for i in range(nn):
        r = _root(parent, i)
        if r == i:
            first[i] = count
            count += 1
        lab[i] = first[r]
        size[lab[i]] += 1
    start = np.zeros(count + 1, np.int64)
    for c in range(count):
        start[c + 1] = start[c] + size[c]
    order = np.empty(nn, np.int64)
    group = np.empty(nn, np.int64)
    for i in range(nn):  # ascending, so each component's nodes stay ascending
        c = lab[i]
        order[start[c]] = i
        group[start[c]] = c
        start[c] += 1
    return order, group, count


@kernel
def _root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]  # path halving; a root is never re-parented here
        i = parent[i]
    return i


def integrate(lmap: LineMap, seg_g: Segments, stamp: int,
              params: MapParams | None = None, seg_l: Segments | None = None,
              node: int | None = None, candidates: np.ndarray | None = None) -> np.ndarray:
    """Fuse global-frame observations into the map (in place). Returns, per observation,
    the index of the map segment it went into (after the update).  With ``seg_l`` (the same
    segments in the laser frame) and ``node``, the observations are kept as contributions;
    ``candidates`` restricts the search to those map indices (e.g. the ones near the scan)."""
    params = params or MapParams()
    k = len(seg_g)
    if k == 0:
        return np.zeros(0, int)
    if candidates is None:
        ok, cost = match_candidates(seg_g.a, seg_g.b, lmap.a, lmap.b, params.merge_angle,
                                    params.merge_dist, params.merge_margin)
        ii, jj = np.nonzero(ok)
    else:
        cand = np.asarray(candidates, dtype=int)
        ok, cost = match_candidates(seg_g.a, seg_g.b, lmap.a[cand], lmap.b[cand],
                                    params.merge_angle, params.merge_dist, params.merge_margin)
        ii, jj = np.nonzero(ok)
    cost = cost[ii, jj]
    if candidates is not None:
        jj = cand[jj]
    is_new = np.ones(k, bool)  # observations that start segments of their own
    target = np.full(k, -1)
    remove: list[int] = []
    redirect_pairs: list[tuple[int, int]] = []
    # items: the observations 0..k-1, then the candidate map segments mj; members come
    # back numbered as observations, then k + map index
    mj, jl = unique_inverse(jj)
    member, group, n_comp = fusions(
        ii, jl + k, cost, np.concatenate([seg_g.n.astype(float), lmap.n_pts[mj]]),
        np.concatenate([seg_g.centroid, lmap.centroid[mj]]),
        np.concatenate([seg_g.scatter, lmap.scatter[mj]]), params.max_residual)
    member = np.where(member < k, member, mj[np.maximum(member - k, 0)] + k)
    is_new[member[member < k]] = False
    if n_comp:
        is_obs = member < k
        o, mi = member[is_obs], member[~is_obs] - k
        go, gm = group[is_obs], group[~is_obs]
        grp = np.concatenate([go, gm])
        N, C, Sm, pa, pb, _ = fuse_groups(
            grp, n_comp, np.concatenate([seg_g.n[o].astype(float), lmap.n_pts[mi]]),
            np.concatenate([seg_g.centroid[o], lmap.centroid[mi]]),
            np.concatenate([seg_g.scatter[o], lmap.scatter[mi]]),
            np.concatenate([seg_g.a[o], lmap.a[mi]]), np.concatenate([seg_g.b[o], lmap.b[mi]]))
        J = np.full(n_comp, len(lmap))
        np.minimum.at(J, gm, mi)  # each group's first map member keeps the fused segment
        lmap.a[J], lmap.b[J], lmap.n_pts[J] = pa, pb, N
        lmap.centroid[J], lmap.scatter[J] = C, Sm
        n_obs = np.bincount(gm, lmap.n_obs[mi], n_comp)
        first = np.full(n_comp, _IMAX)
        np.minimum.at(first, gm, lmap.created[mi])
        lmap.n_obs[J] = n_obs.astype(int) + 1
        lmap.created[J] = first
        lmap.last_seen[J] = stamp
        lmap.through[J] = 0  # seen again
        target[o] = J[go]
        rest = mi != J[gm]
        remove.extend(mi[rest].tolist())
        redirect_pairs.extend(zip(mi[rest].tolist(), J[gm[rest]].tolist(), strict=True))
    new = np.nonzero(is_new)[0]
    start = len(lmap)
    lmap.append(seg_g.subset(new), stamp)
    target[new] = start + np.arange(len(new))
    if seg_l is not None and node is not None:
        lmap.add_contributions(target, node, seg_l)
    if remove:
        keep = np.ones(len(lmap), bool)
        keep[remove] = False
        remap = np.cumsum(keep) - 1
        target = remap[target]
        _fold(lmap, keep, remap, redirect_pairs)
    return target


def _fold(lmap: LineMap, keep: np.ndarray, remap: np.ndarray,
          pairs: list[tuple[int, int]]) -> None:
    """Drop the segments not in ``keep`` (``remap``: ``cumsum(keep) - 1``), each of them
    fused into another: ``pairs`` (gone, kept) point their contributions at the segment they
    went into, renumbered.  The contribution rows stay where they are: one pass over their
    segment numbers, where redirecting and then subsetting made three (tens of thousands
    of rows, on a third of the scans)."""
    red = np.arange(len(lmap))
    for r, j0 in pairs:
        red[r] = j0
    out = lmap._rows(keep)
    out.c_seg = remap[red][lmap.c_seg]
    _assign(lmap, out)


_FIELDS = ("a", "b", "n_pts", "centroid", "scatter", "n_obs", "created", "last_seen",
           "c_seg", "c_node", "c_n", "c_cent", "c_scat", "c_a", "c_b", "through")


def _assign(dst: LineMap, src: LineMap) -> None:
    for name in _FIELDS:
        setattr(dst, name, getattr(src, name))


def copies(a: np.ndarray, b: np.ndarray, dist: float = 0.03, angle_deg: float = 5.0,
           chunk: int = 256) -> int:
    """How many segments a-b have a copy: another segment within ``angle_deg`` of their
    direction, both its end points within ``dist`` of their line, overlapping them along it
    by more than 5 cm.  A map that stays clean on revisits has (almost) none within a few
    centimetres.  Rows in chunks: (chunk, n) temporaries, not (n, n)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    d = b - a
    L = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    u = d / L[:, None]
    nrm = np.column_stack([-u[:, 1], u[:, 0]])
    found = 0
    for r0 in range(0, len(a), chunk):
        r = slice(r0, r0 + chunk)
        pa, pb = a[None] - a[r, None], b[None] - a[r, None]            # (k, n, 2)
        off_a = np.abs(np.einsum("ik,ijk->ij", nrm[r], pa))
        off_b = np.abs(np.einsum("ik,ijk->ij", nrm[r], pb))
        ta, tb = np.einsum("ik,ijk->ij", u[r], pa), np.einsum("ik,ijk->ij", u[r], pb)
        overlap = (np.minimum(np.maximum(ta, tb), L[r, None])
                   - np.maximum(np.minimum(ta, tb), 0.0))
        twin = ((np.abs(u[r] @ u.T) > np.cos(np.deg2rad(angle_deg))) & (off_a < dist)
                & (off_b < dist) & (overlap > 0.05))
        twin[np.arange(twin.shape[0]), np.arange(r0, r0 + twin.shape[0])] = False
        found += int(twin.any(axis=1).sum())
    return found


def age_out(lmap: LineMap, stamp: int, params: MapParams | None = None,
            travel: np.ndarray | None = None, turned: np.ndarray | None = None,
            retired: list | None = None) -> int:
    """Drop segments seen only once long enough ago that are short; segments seen only
    in the few scans after they appeared (``age_seen`` times at most) when those scans
    looked from nearly where they were seen (``travel``: odometry travel per scan stamp up
    to ``stamp``, and ``turned``, its turn, if given; see ``MapParams.age_travel``); and
    segments the laser has seen through in ``params.clear.scans`` scans in a row
    (:mod:`.free_space`); returns how many went.  With ``retired``, the contributions
    (node, end a, end b) of the segments dropped for being seen only in those few scans are
    appended to it as one tuple of arrays: they were seen, and a loop closure's submap of
    that place still wants them."""
    params = params or MapParams()
    c = lmap.created
    judged = stamp - c > params.age_scans
    drop = judged & (lmap.n_obs <= 1) & (lmap.length < params.age_min_length)
    # seen at most age_seen times, all in its first age_scans scans; adopted segments
    # (stamps before this run) have no travel here: length alone
    few = judged & (c >= 0) & (lmap.n_obs <= max(params.age_seen, 1)) & (
        lmap.last_seen <= c + params.age_scans)
    if travel is not None and params.age_travel > 0 and len(travel) > stamp and few.any():
        end, start = np.clip(c + params.age_scans, 0, stamp), np.clip(c, 0, stamp)
        near = travel[end] - travel[start] <= params.age_travel
        if turned is not None and len(turned) > stamp:
            near &= turned[end] - turned[start] <= params.age_turn
        glimpse = few & near & ~drop
        if params.clear.enabled:
            glimpse &= lmap.through < params.clear.scans  # seen through: gone, not retired
        if retired is not None and glimpse.any() and len(lmap.c_seg):
            rows = glimpse[lmap.c_seg]
            retired.append((lmap.c_node[rows], lmap.c_a[rows], lmap.c_b[rows]))
        drop |= glimpse
    if params.clear.enabled:
        drop |= lmap.through >= params.clear.scans
    if drop.any():
        _assign(lmap, lmap.subset(~drop))
    return int(drop.sum())


def dedupe(lmap: LineMap, params: MapParams | None = None, since: int | None = None) -> int:
    """Fuse map segments that coincide (same wall twice); returns how many were removed.
    With ``since``, only segments seen at or after that stamp are compared (against all)."""
    params = params or MapParams()
    m = len(lmap)
    if m < 2:
        return 0
    rec = np.arange(m) if since is None else np.nonzero(lmap.last_seen >= since)[0]
    if not len(rec):
        return 0
    ok_r, cost_r = match_candidates(lmap.a[rec], lmap.b[rec], lmap.a, lmap.b,
                                    params.merge_angle, params.merge_dist, params.dedupe_margin)
    ok_t, _ = match_candidates(lmap.a, lmap.b, lmap.a[rec], lmap.b[rec], params.merge_angle,
                               params.merge_dist, params.dedupe_margin)
    ok_r &= ok_t.T  # both ways: each lies along the other
    ok_r[np.arange(len(rec)), rec] = False
    ii, jj = np.nonzero(ok_r)
    cost = cost_r[ii, jj]
    ii = rec[ii]
    if not len(ii):
        return 0
    member, group, n_comp = fusions(ii, jj, cost, lmap.n_pts, lmap.centroid, lmap.scatter,
                                    params.max_residual)
    if not n_comp:
        return 0
    N, C, S, pa, pb, _ = fuse_groups(group, n_comp, lmap.n_pts[member], lmap.centroid[member],
                                     lmap.scatter[member], lmap.a[member], lmap.b[member])
    # members are ascending: each group's first keeps the segment
    J = member[np.flatnonzero(np.concatenate([[True], group[1:] != group[:-1]]))]
    n_obs = np.bincount(group, lmap.n_obs[member], n_comp).astype(int)
    first = np.full(n_comp, _IMAX)
    last = np.full(n_comp, _IMIN)
    np.minimum.at(first, group, lmap.created[member])
    np.maximum.at(last, group, lmap.last_seen[member])
    lmap.a[J], lmap.b[J], lmap.n_pts[J], lmap.centroid[J], lmap.scatter[J] = pa, pb, N, C, S
    lmap.n_obs[J], lmap.created[J], lmap.last_seen[J] = n_obs, first, last
    through = np.full(n_comp, _IMAX)
    np.minimum.at(through, group, lmap.through[member])
    lmap.through[J] = through
    rest = member != J[group]
    remove = member[rest].tolist()
    keep = np.ones(m, bool)
    keep[remove] = False
    _fold(lmap, keep, np.cumsum(keep) - 1,
          list(zip(remove, J[group[rest]].tolist(), strict=True)))
    return len(remove)


def refresh(lmap: LineMap, poses: np.ndarray) -> None:
    """Recompute every segment from its contributions seen from ``poses`` (n, 3) (laser
    poses of the nodes): moments add up per segment, TLS refit, union of extents.

    Contributions with a negative node (frozen: from a map loaded or handed over, whose scans
    are not in this run's graph) are left out; a segment with only frozen contributions keeps
    its geometry."""
    live = lmap.c_node >= 0
    if not live.any():
        return
    if not live.all():
        frozen = LineMap(lmap.a, lmap.b, lmap.n_pts, lmap.centroid, lmap.scatter, lmap.n_obs,
                         lmap.created, lmap.last_seen)
        frozen.c_seg, frozen.c_node, frozen.c_n = (lmap.c_seg[live], lmap.c_node[live],
                                                    lmap.c_n[live])
        frozen.c_cent, frozen.c_scat = lmap.c_cent[live], lmap.c_scat[live]
        frozen.c_a, frozen.c_b = lmap.c_a[live], lmap.c_b[live]
        refresh(frozen, poses)
        for name in ("a", "b", "n_pts", "centroid", "scatter"):
            setattr(lmap, name, getattr(frozen, name))
        return
    P = np.asarray(poses)[lmap.c_node]
    c, s = np.cos(P[:, 2]), np.sin(P[:, 2])
    R = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)
    t = P[:, :2]
    cg = np.einsum("kij,kj->ki", R, lmap.c_cent) + t
    Sg = R @ lmap.c_scat @ np.swapaxes(R, 1, 2)
    ag = np.einsum("kij,kj->ki", R, lmap.c_a) + t
    bg = np.einsum("kij,kj->ki", R, lmap.c_b) + t
    N, C, S, pa, pb, _ = fuse_groups(lmap.c_seg, len(lmap), lmap.c_n, cg, Sg, ag, bg)
    has = N > 0
    lmap.n_pts = np.where(has, N, lmap.n_pts)
    lmap.centroid = np.where(has[:, None], C, lmap.centroid)
    lmap.scatter = np.where(has[:, None, None], S, lmap.scatter)
    lmap.a = np.where(has[:, None], pa, lmap.a)
    lmap.b = np.where(has[:, None], pb, lmap.b)
