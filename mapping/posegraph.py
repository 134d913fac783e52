"""A 2D pose graph: nodes are scan poses, edges relative-pose measurements with information.

The seeds' global-map matching pulls the pose back when the robot returns to a mapped place,
but drift accumulated on the way is already in the map.  Closing the loop spreads that
correction over the trajectory: sequential edges come from the scan-to-map corrections
(eqs. 10-11), loop edges from matching a scan against the segments of an earlier visit, and
the graph is solved by Gauss-Newton with a sparse normal matrix (robust Cauchy weights on the
loop edges so that a wrong closure cannot bend the map).  The map segments are anchored to
the scans that observed them (:mod:`.linemap`), so the map follows the optimised poses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from .odometry import relative
from .odometry import wrap_angle as wrap

# Cauchy scale of the loop edges' Mahalanobis distance, shared by every solve of the graph
ROBUST_SCALE = 3.0
# normal equations up to this many unknowns are factored (SuperLU); larger ones go to
# conjugate gradients first.  A graph a robot has driven around for hours ties every node to
# scans of every lap: the factor fills in (18 000 nodes, 600 000 neighbour edges: no SuperLU
# solve in 10 min) while CG converges in under a hundred steps (1.4 s, 320 MB)
DIRECT_MAX = 9000
# the same graph before its neighbour pass (the chain and its closures, 560 000 non-zeros)
# needs ~600 steps (2 s); SuperLU takes 11 s there, so CG is given that many and more
CG_ITERATIONS = 1500
CG_TOLERANCE = 1e-9


def solve_normal(H: sp.spmatrix, b: np.ndarray, blocks: int) -> np.ndarray:
    """x with H x = b for symmetric positive definite normal equations whose first
    ``blocks`` 3x3 diagonal blocks are poses and whose unknowns after them are lines, 2x2
    blocks (phi, rho): factored when small, else preconditioned conjugate gradients (block
    Jacobi), falling back to the factor when CG does not converge (a long chain with few
    closures, which factors cheaply)."""
    if H.shape[0] <= DIRECT_MAX:
        return spsolve(H.tocsc(), b)
    A = H.tocsr()
    x, ok = _pcg(A, b, _block_jacobi(A, blocks))
    return x if ok else spsolve(H.tocsc(), b)


def _diagonal_blocks(A: sp.csr_matrix, start: int, count: int, size: int) -> np.ndarray:
    """A's ``count`` diagonal blocks of ``size`` x ``size`` from row ``start`` on."""
    r = start + size * np.arange(count)
    B = np.empty((count, size, size))
    for a in range(size):
        for c in range(size):
            B[:, a, c] = np.asarray(A[r + a, r + c]).ravel()
    return B


def _block_jacobi(A: sp.csr_matrix, blocks: int):
    """The inverse of A's 3x3 pose blocks and of its 2x2 line blocks after them, as an
    operator.  A line's (phi, rho) must be one block: for a wall 20 m from the origin a turn
    of phi moves it by 20 m times the angle unless rho follows, and a diagonal preconditioner
    left CG short of convergence after 1 500 steps on the Intel log driven four times
    (3 640 poses, 800 lines; the factor then took 6 s a step), where the blocks converge in
    about 0.4 s."""
    Binv = np.linalg.pinv(_diagonal_blocks(A, 0, blocks, 3) + 1e-12 * np.eye(3),
                          hermitian=True)
    lines = (A.shape[0] - 3 * blocks) // 2
    Linv = np.linalg.pinv(_diagonal_blocks(A, 3 * blocks, lines, 2), hermitian=True)

    def apply(v: np.ndarray) -> np.ndarray:
        head = np.einsum("kij,kj->ki", Binv, v[:3 * blocks].reshape(-1, 3)).ravel()
        tail = np.einsum("kij,kj->ki", Linv, v[3 * blocks:].reshape(-1, 2)).ravel()
        return np.concatenate([head, tail])
    return apply


def _pcg(A: sp.csr_matrix, b: np.ndarray, M) -> tuple[np.ndarray, bool]:
    """Preconditioned conjugate gradients from zero; (x, converged)."""
    x = np.zeros_like(b)
    r = b.copy()
    z = M(r)
    p = z.copy()
    rz = r @ z
    stop = CG_TOLERANCE * np.linalg.norm(b)
    for _ in range(CG_ITERATIONS):
        if np.linalg.norm(r) <= stop:
            return x, True
        Ap = A @ p
        alpha = rz / (p @ Ap)
        x += alpha * p
        r -= alpha * Ap
        z = M(r)
        rz, rz_old = r @ z, rz
        p = z + (rz / rz_old) * p
    return x, bool(np.linalg.norm(r) <= stop)


@dataclass(frozen=True)
class EdgeArrays:
    """A graph's edges as arrays: (k,) node indices i, j, (k, 3) measurements, (k, 3, 3)
    information, (k,) robust (loop) flags."""

    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    info: np.ndarray
    robust: np.ndarray
    _layouts: dict = field(default_factory=dict, compare=False, repr=False)

    def __len__(self) -> int:
        return len(self.i)

    @classmethod
    def of(cls, i, j, z, info, robust=True) -> EdgeArrays:
        """Edges from array-likes; ``robust`` one flag for all or one per edge."""
        i = np.asarray(i, np.int64).reshape(-1)
        return cls(i, np.asarray(j, np.int64).reshape(-1), np.asarray(z, float).reshape(-1, 3),
                   np.asarray(info, float).reshape(-1, 3, 3),
                   np.broadcast_to(np.asarray(robust, bool), i.shape).copy())

    @classmethod
    def empty(cls) -> EdgeArrays:
        return cls.of([], [], [], [])

    @classmethod
    def concat(cls, parts: list[EdgeArrays]) -> EdgeArrays:
        parts = [p for p in parts if len(p)]
        if not parts:
            return cls.empty()
        return cls(*(np.concatenate([getattr(p, f) for p in parts])
                     for f in ("i", "j", "z", "info", "robust")))

    def select(self, idx) -> EdgeArrays:
        return EdgeArrays(self.i[idx], self.j[idx], self.z[idx], self.info[idx],
                          self.robust[idx])

    def layout(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Where the edges' 3x3 blocks go in the (3n, 3n) normal matrix, the same at every
        iteration: for the blocks (i,i), (j,j), (i,j), (j,i) of every edge, in that order,
        the index of the place they are summed into; the places' columns and row pointers
        (BSR, by block); their number."""
        if n not in self._layouts:
            keys = np.concatenate([self.i * (n + 1), self.j * (n + 1), self.i * n + self.j,
                                   self.j * n + self.i])
            u, inv = np.unique(keys, return_inverse=True)
            rows, cols = np.divmod(u, n)
            self._layouts[n] = (inv, cols, np.searchsorted(rows, np.arange(n + 1)), len(u))
        return self._layouts[n]


class Column:
    """A growable column of same-shaped rows in one numpy buffer, used like a list (append,
    index, assign, delete a slice, iterate; ``np.asarray`` gives the rows without a copy).

    A graph a daemon keeps for months has some 600 000 edges: as lists of small arrays they
    took ~420 bytes each (a Python object per measurement and per information matrix), as
    columns 113 plus the room to grow (at most as much again), and handing them to a solve
    costs no conversion.  Rows read by index are
    views: like a list's elements they see assignments, but not after the buffer grows."""

    def __init__(self, shape: tuple = (), dtype=float, rows=None):
        self._buf = np.empty((16, *shape), dtype)
        self._n = 0
        if rows is not None:
            self.extend(rows)

    def __len__(self) -> int:
        return self._n

    def _reserve(self, n: int) -> None:
        if n > len(self._buf):
            buf = np.empty((max(n, 2 * len(self._buf)), *self._buf.shape[1:]), self._buf.dtype)
            buf[:self._n] = self._buf[:self._n]
            self._buf = buf

    def append(self, row) -> None:
        self._reserve(self._n + 1)
        self._buf[self._n] = row
        self._n += 1

    def extend(self, rows) -> None:
        rows = np.asarray(rows if not isinstance(rows, Column) else rows.array(),
                          self._buf.dtype).reshape(-1, *self._buf.shape[1:])
        self._reserve(self._n + len(rows))
        self._buf[self._n:self._n + len(rows)] = rows
        self._n += len(rows)

    def array(self) -> np.ndarray:
        """The rows (a view)."""
        return self._buf[:self._n]

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        a = self.array()
        if dtype is not None and np.dtype(dtype) != a.dtype:
            return a.astype(dtype)
        return a.copy() if copy else a

    def __getitem__(self, k):
        return self.array()[k]

    def __setitem__(self, k, value) -> None:
        self.array()[k] = value

    def __delitem__(self, k) -> None:
        keep = np.ones(self._n, bool)
        keep[k] = False
        m = int(keep.sum())
        self._buf[:m] = self._buf[:self._n][keep]
        self._n = m

    def __iter__(self):
        return iter(self.array())

    def copy(self) -> Column:
        return Column(self._buf.shape[1:], self._buf.dtype, self.array())


def _column(rows, shape: tuple, dtype) -> Column:
    if isinstance(rows, Column):
        return rows
    return Column(shape, dtype, None if rows is None or len(rows) == 0 else rows)


class PoseGraph:
    """Poses (n, 3) and edges: node indices ``ei``, ``ej``, measured relative poses ``z``
    (3,), information ``info`` (3, 3) and robust (loop) flags ``loop``, each a
    :class:`Column`; lists given to the constructor or assigned are converted."""

    _COLUMNS = {"poses": ((3,), float), "ei": ((), np.int64), "ej": ((), np.int64),
                "z": ((3,), float), "info": ((3, 3), float), "loop": ((), bool)}

    def __init__(self, poses=None, ei=None, ej=None, z=None, info=None, loop=None):
        for name, value in zip(self._COLUMNS, (poses, ei, ej, z, info, loop), strict=True):
            setattr(self, name, value)

    def __setattr__(self, name, value) -> None:
        if name in self._COLUMNS:
            value = _column(value, *self._COLUMNS[name])
        object.__setattr__(self, name, value)

    def copy(self) -> PoseGraph:
        return PoseGraph(*(getattr(self, name).copy() for name in self._COLUMNS))

    def add_node(self, pose) -> int:
        self.poses.append(pose)
        return len(self.poses) - 1

    def add_edge(self, i: int, j: int, z, info, loop: bool = False) -> None:
        self.ei.append(i)
        self.ej.append(j)
        self.z.append(z)
        self.info.append(info)
        self.loop.append(loop)

    def add_edges(self, edges: EdgeArrays) -> None:
        """Append many edges at once (their ``robust`` flags as the loop flags)."""
        self.ei.extend(edges.i)
        self.ej.extend(edges.j)
        self.z.extend(edges.z)
        self.info.extend(edges.info)
        self.loop.extend(edges.robust)

    def edge_arrays(self) -> EdgeArrays:
        """The edges as arrays (copies: a solve's layout cache must not see later edits)."""
        return EdgeArrays(np.array(self.ei, np.int64), np.array(self.ej, np.int64),
                          np.array(self.z, float), np.array(self.info, float),
                          np.array(self.loop, bool))

    def residuals(self, X: np.ndarray | None = None) -> np.ndarray:
        X = np.array(self.poses) if X is None else X
        E = self.edge_arrays()
        e = relative(X[E.i], X[E.j]) - E.z
        e[:, 2] = wrap(e[:, 2])
        return e

    def normal_equations(self, X: np.ndarray, robust_scale: float | np.ndarray,
                         edges: EdgeArrays | None = None, chunk: int = 1 << 16
                         ) -> tuple[sp.csr_matrix, np.ndarray, float]:
        """Gauss-Newton normal equations of the edges at poses ``X`` (n, 3): the sparse
        (3n, 3n) information H, the gradient g (the step solves H dx = -g) and the weighted
        chi^2; loop edges carry Cauchy weights of scale ``robust_scale`` (one, or one per
        edge).  No node is held.
        ``edges``: :meth:`edge_arrays`, when the caller solves repeatedly.  The edges are
        taken ``chunk`` at a time: each edge's Jacobian blocks and products take ~430 bytes,
        and a daemon's graph has 600 000 edges."""
        n = len(X)
        E = self.edge_arrays() if edges is None else edges
        k = len(E.i)
        # 3x3 blocks: each edge's two diagonal blocks, its coupling block and that block's
        # transpose, summed where they share a place (:meth:`EdgeArrays.layout`)
        inv, cols, indptr, nb = E.layout(n)
        data = np.zeros((nb, 9))
        g = np.zeros(3 * n)
        chi2 = 0.0
        r3 = np.arange(3)
        scale2 = np.broadcast_to(np.asarray(robust_scale, float) ** 2, (k,))
        for c0 in range(0, k, chunk):
            c1 = min(c0 + chunk, k)
            i, j = E.i[c0:c1], E.j[c0:c1]
            e = relative(X[i], X[j]) - E.z[c0:c1]
            e[:, 2] = wrap(e[:, 2])
            info = E.info[c0:c1]
            m2 = np.einsum("ki,kij,kj->k", e, info, e)
            w = np.where(E.robust[c0:c1], 1.0 / (1.0 + m2 / scale2[c0:c1]), 1.0)
            chi2 += float(np.sum(w * m2))
            c, s = np.cos(X[i, 2]), np.sin(X[i, 2])
            d = X[j, :2] - X[i, :2]
            A = np.zeros((len(i), 3, 3))   # de/dx_i
            B = np.zeros((len(i), 3, 3))   # de/dx_j
            A[:, 0, 0], A[:, 0, 1] = -c, -s
            A[:, 1, 0], A[:, 1, 1] = s, -c
            A[:, 0, 2] = -s * d[:, 0] + c * d[:, 1]
            A[:, 1, 2] = -c * d[:, 0] - s * d[:, 1]
            A[:, 2, 2] = -1.0
            B[:, 0, 0], B[:, 0, 1] = c, s
            B[:, 1, 0], B[:, 1, 1] = -s, c
            B[:, 2, 2] = 1.0
            Wo = info * w[:, None, None]
            AtW, BtW = np.swapaxes(A, 1, 2) @ Wo, np.swapaxes(B, 1, 2) @ Wo
            del Wo
            g += (np.bincount((3 * i[:, None] + r3).ravel(),
                              np.einsum("kij,kj->ki", AtW, e).ravel(), 3 * n)
                  + np.bincount((3 * j[:, None] + r3).ravel(),
                                np.einsum("kij,kj->ki", BtW, e).ravel(), 3 * n))
            Hij = AtW @ B
            for part, M in enumerate((AtW @ A, BtW @ B, Hij, np.swapaxes(Hij, 1, 2))):
                at, M = inv[part * k + c0:part * k + c1], M.reshape(c1 - c0, 9)
                for q in range(9):
                    data[:, q] += np.bincount(at, M[:, q], nb)
            del A, B, AtW, BtW, Hij, M
        H = sp.bsr_matrix((data.reshape(-1, 3, 3), cols, indptr), shape=(3 * n,) * 2).tocsr()
        return H, g, chi2

    def optimize(self, iterations: int = 10, robust_scale: float = ROBUST_SCALE,
                 fixed: int | list[int] = 0, free_from: int = 0, judged: int = 0) -> dict:
        """Gauss-Newton over all poses (the ``fixed`` node or nodes held); updates ``poses``
        in place.  ``free_from`` > 0 solves only the nodes from there on: the older nodes
        stay where they are, and those tied to the free ones by an edge are held, so the
        cost follows the free nodes and their edges, not the whole graph.  The first
        iterations trust every closure (graduated), except the first ``judged`` edges: an
        earlier solve has weighed them already."""
        n = len(self.poses)
        if n < 2 or not self.ei:
            return {"iterations": 0, "chi2": 0.0}
        fresh = np.arange(len(self.ei)) >= judged
        if free_from > 0:
            return self._optimize_window(iterations, robust_scale, fixed, free_from, fresh)
        return self._gauss_newton(iterations, robust_scale, fixed, fresh=fresh)

    def _gauss_newton(self, iterations: int, robust_scale: float, fixed: int | list[int],
                      known: int = 0, fresh: np.ndarray | None = None) -> dict:
        """:meth:`optimize`'s iterations.  The first ``known`` nodes are no unknowns: they
        stay where they are, and their edges to the others act as priors on those (a
        window's boundary may be thousands of nodes, which a stiff prior per node would
        leave in the system, and CG does not converge on that).  ``fresh``: the edges the
        graduated first iterations trust (default all)."""
        n = len(self.poses)
        X = np.array(self.poses)
        m = n - known
        fx = [int(f) - known for f in np.atleast_1d(fixed) if int(f) >= known]
        hold = hold_nodes(fx, m) if fx else None
        E = self.edge_arrays()
        chi2 = 0.0
        wide = robust_scale * (30.0 if fresh is None else np.where(fresh, 30.0, 1.0))
        for it in range(iterations):
            # graduated: the first passes trust every new closure (a true one can disagree
            # by metres before the graph has moved), then the Cauchy weights sort out the
            # rest.  A closure an earlier solve found wrong is not trusted again: two wrong
            # ones on Intel moved the graph 0.7 m at every online solve, and the next eight
            # iterations took it back
            H, g, chi2 = self.normal_equations(X, wide if it < 2 else robust_scale, E)
            if known:
                H, g = H[3 * known:, 3 * known:], g[3 * known:]
            if hold is not None:
                H = H + hold   # rebound: the matrix without the prior is freed before the solve
            dx = solve_normal(H, -g, m).reshape(m, 3)
            del H
            X[known:] += dx
            X[:, 2] = wrap(X[:, 2])
            if it >= 2 and np.max(np.abs(dx)) < 1e-5:
                break
        self.poses = X
        return {"iterations": it + 1, "chi2": chi2}

    def _optimize_window(self, iterations: int, robust_scale: float,
                         fixed: int | list[int], free_from: int, fresh: np.ndarray) -> dict:
        ei, ej = self.ei.array(), self.ej.array()
        sel = np.nonzero(np.maximum(ei, ej) >= free_from)[0]
        if not len(sel):
            return {"iterations": 0, "chi2": 0.0, "nodes": 0}
        nodes = np.union1d(np.unique(np.concatenate([ei[sel], ej[sel]])),
                           np.arange(free_from, len(self.poses)))
        # the nodes in ascending order: the held ones (older than the window) come first
        known = int(np.sum(nodes < free_from))
        fx = [int(np.searchsorted(nodes, k)) for k in np.atleast_1d(fixed)
              if k >= free_from and k < len(self.poses)]
        sub = PoseGraph(self.poses[nodes], np.searchsorted(nodes, ei[sel]),
                        np.searchsorted(nodes, ej[sel]), self.z[sel], self.info[sel],
                        self.loop[sel])
        got = sub._gauss_newton(iterations, robust_scale, fx or ([] if known else [0]), known,
                                fresh[sel])
        free = nodes >= free_from
        self.poses[nodes[free]] = sub.poses[free]
        return {**got, "nodes": int(np.sum(free))}


def hold_nodes(fixed: int | list[int], n: int, size: int | None = None) -> sp.csc_matrix:
    """A stiff prior holding the ``fixed`` node(s) of n poses, as a (size, size) diagonal
    (size defaults to 3n; more variables may follow the poses)."""
    fx = np.atleast_1d(np.asarray(fixed, dtype=int))
    idx = (3 * fx[:, None] + np.arange(3)).ravel()
    size = 3 * n if size is None else size
    return sp.csc_matrix((np.full(len(idx), 1e9), (idx, idx)), shape=(size, size))
