"""The compiled kernels (mapping/jit.py): what they compute, checked against plain numpy,
and how they behave where numba cannot cache."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from cgamap.mapping import jit
from cgamap.mapping.linemap import fuse_groups, unique_inverse
from cgamap.mapping.matching import LineIndex, match_index, near_box, near_segments


def test_fused_groups_are_the_fit_of_all_their_points():
    """Three groups of point sets: each group's count, centroid, scatter and line are those
    of all its points together, its end points the extreme projections of its members'."""
    rng = np.random.default_rng(5)
    sets, group = [], []
    for g, (angle, offset) in enumerate([(0.3, 1.0), (1.2, -2.0), (2.5, 0.5)]):
        d = np.array([np.cos(angle), np.sin(angle)])
        nrm = np.array([-d[1], d[0]])
        for _ in range(rng.integers(1, 4)):
            t = np.sort(rng.uniform(-3, 3, rng.integers(3, 30)))
            sets.append(t[:, None] * d + offset * nrm + rng.normal(0, 0.01, (len(t), 1)) * nrm)
            group.append(g)
    group = np.array(group)
    n = np.array([len(p) for p in sets], float)
    c = np.array([p.mean(0) for p in sets])
    S = np.array([(p - p.mean(0)).T @ (p - p.mean(0)) for p in sets])
    a = np.array([s[0] for s in sets])
    b = np.array([s[-1] for s in sets])
    N, C, Sg, pa, pb, rms = fuse_groups(group, 4, n, c, S, a, b)  # group 3 has no member
    for g in range(3):
        p = np.concatenate([s for s, k in zip(sets, group, strict=True) if k == g])
        assert N[g] == len(p)
        assert np.allclose(C[g], p.mean(0), atol=1e-12)
        q = p - p.mean(0)
        assert np.allclose(Sg[g], q.T @ q, atol=1e-9)
        w, v = np.linalg.eigh(q.T @ q)
        assert np.isclose(rms[g], np.sqrt(w[0] / len(p)), atol=1e-12)
        d = v[:, 1]
        ends = np.concatenate([a[group == g], b[group == g]]) - C[g]
        span = sorted([pa[g] - C[g], pb[g] - C[g]], key=lambda e: e @ d)
        assert np.isclose(span[0] @ d, (ends @ d).min(), atol=1e-9)
        assert np.isclose(span[1] @ d, (ends @ d).max(), atol=1e-9)
        e = pb[g] - pa[g]
        assert abs(e[0] * d[1] - e[1] * d[0]) < 1e-9  # the end points lie on the line
    assert N[3] == 0 and np.allclose(pa[3], pb[3])


def test_match_index_broadcasts_a_batch_like_its_elements():
    """One scan against a batch of three segment sets: each element of the batched result
    is what that set gives alone."""
    rng = np.random.default_rng(2)
    a1 = rng.uniform(-2, 2, (6, 2))
    b1 = a1 + rng.normal(0, 0.5, (6, 2))
    a2 = a1[None] + rng.normal(0, 0.05, (3, 6, 2))
    b2 = b1[None] + rng.normal(0, 0.05, (3, 6, 2))
    ok, cost = match_index(a1, b1, LineIndex.of(a2, b2), np.deg2rad(10), 0.1)
    assert ok.shape == (3, 6, 6) and ok.any()
    for q in range(3):
        ok_q, cost_q = match_index(a1, b1, LineIndex.of(a2[q], b2[q]), np.deg2rad(10), 0.1)
        assert np.array_equal(ok[q], ok_q) and np.array_equal(cost[q], cost_q)
    assert np.all(np.isinf(cost[~ok]))


def test_a_kernel_compiles_in_memory_where_nothing_can_cache(monkeypatch):
    """No cache location (a read-only install, no NUMBA_CACHE_DIR, no home): a warning and
    a kernel that works, not an error at import."""
    caching = pytest.importorskip("numba.core.caching")
    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    if impl is None or not hasattr(impl, "_locator_classes"):
        pytest.skip("this numba keeps its cache locators elsewhere")
    monkeypatch.setattr(impl, "_locator_classes", [])
    monkeypatch.delenv("NUMBA_CACHE_LOCATOR_CLASSES", raising=False)

    def twice(x):
        return 2 * x

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        k = jit.kernel(twice)
    assert any("compiling in memory" in str(w.message) for w in caught)
    assert k(21) == 42


def test_warm_up_leaves_no_kernel_to_compile_on_a_scan():
    """Every kernel the mapping modules call from Python has a compiled signature after
    warm_up (a kernel added without a place in warm_up would compile on the daemon's first
    scan)."""
    from cgamap.mapping import correction, linemap, matching, segments

    jit.warm_up()
    kernels = {f"{m.__name__}.{name}": v for m in (correction, linemap, matching, segments)
               for name, v in vars(m).items() if hasattr(v, "py_func") and
               hasattr(v, "signatures")}
    assert len(kernels) >= 10
    # helpers that only other kernels call are compiled into their callers
    inner = {n for k in kernels.values() for n in k.py_func.__code__.co_names}
    assert not [name for name, k in kernels.items()
                if not k.signatures and name.rsplit(".", 1)[1] not in inner]


def test_near_segments_is_near_box_on_end_points():
    """The compiled first cut picks exactly the segments the array one picks, from the end
    points alone (centres and half lengths computed the same way on the way)."""
    rng = np.random.default_rng(11)
    ma = rng.uniform(-30, 30, (800, 2))
    mb = ma + rng.normal(0, 2, (800, 2))
    for _ in range(20):
        a = rng.uniform(-5, 5, (12, 2)) + rng.uniform(-20, 20, 2)
        b = a + rng.normal(0, 1, (12, 2))
        reach = float(rng.uniform(0.1, 3))
        want = near_box(0.5 * (ma + mb), 0.5 * np.linalg.norm(mb - ma, axis=-1), a, b, reach)
        got = near_segments(ma, mb, a, b, reach)
        assert np.array_equal(got, want) and len(want)
    assert len(near_segments(ma[:0], mb[:0], a, b, 1.0)) == 0


def test_unique_inverse_is_numpys():
    rng = np.random.default_rng(12)
    for n in (0, 1, 2, 7, 60, 400):
        for _ in range(20):
            x = rng.integers(0, 50, n)
            want = np.unique(x, return_inverse=True)
            got = unique_inverse(x)
            assert all(np.array_equal(g, w) and g.dtype == w.dtype
                       for g, w in zip(got, want, strict=True))
