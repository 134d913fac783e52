"""Line map files: versioned JSON with end points, CGA coefficients, counts and metadata.

Layout (version 1)::

    {"format": "cgamap.linemap", "version": 1, "metadata": {...},
     "segments": [{"a": [x, y], "b": [x, y], "n_obs": 3, "n_points": 41.0,
                   "centroid": [x, y], "scatter": [sxx, sxy, syy],
                   "hough": [theta, rho],
                   "cga": {"point_pair": {"e1+": ..}, "line": {..}, "sphere": {..}}}, ...]}

The CGA entities (OPNS point pair up(a)^up(b), its line PP^einf (eq. 28) and its IPNS sphere
(eq. 12)) are stored by blade name, non-zero coefficients only.  Loading validates every
field and rejects a malformed file with one clear message naming the file and the field; the
end points are authoritative and the stored point pair must agree with them.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from cgamap.cga import BLADE_NAMES

from .cga_segments import cga_segments
from .fileio import write_text_atomic
from .linemap import LineMap
from .segments import Segments

FORMAT = "cgamap.linemap"
VERSION = 1


class MapFormatError(ValueError):
    """A map file that cannot be loaded; the message names the file and the field."""


def _blades(v: np.ndarray, tol: float = 1e-12) -> dict[str, float]:
    return {BLADE_NAMES[i]: round(float(x), 9) for i, x in enumerate(v) if abs(x) > tol}


def _as_segments(lmap: LineMap) -> Segments:
    m = len(lmap)
    return Segments(lmap.a, lmap.b, lmap.n_pts.astype(int), np.zeros(m), lmap.centroid,
                    lmap.scatter, np.zeros((m, 2, 2)))


def map_to_json(lmap: LineMap, metadata: dict | None = None) -> dict:
    meta = dict(lmap.metadata)
    meta.update(metadata or {})
    segs = []
    if len(lmap):
        cg = cga_segments(_as_segments(lmap))
        for i in range(len(lmap)):
            S = lmap.scatter[i]
            segs.append({
                "a": [round(float(v), 6) for v in lmap.a[i]],
                "b": [round(float(v), 6) for v in lmap.b[i]],
                "n_obs": int(lmap.n_obs[i]),
                "n_points": float(lmap.n_pts[i]),
                "centroid": [round(float(v), 6) for v in lmap.centroid[i]],
                "scatter": [float(S[0, 0]), float(S[0, 1]), float(S[1, 1])],
                "hough": [round(float(cg.theta[i]), 9), round(float(cg.rho[i]), 9)],
                "cga": {"point_pair": _blades(cg.pairs.v[i]), "line": _blades(cg.lines.v[i]),
                        "sphere": _blades(cg.spheres.v[i])},
            })
    return {"format": FORMAT, "version": VERSION, "metadata": meta, "segments": segs}


def save_map(lmap: LineMap, path: str | Path, metadata: dict | None = None) -> None:
    """Write atomically (temp file + rename) so a reader never sees half a map."""
    doc = map_to_json(lmap, metadata)
    write_text_atomic(path, json.dumps(doc, separators=(",", ":")), mode=0o644)


def _vec(seg: dict, key: str, n: int, where: str) -> np.ndarray:
    v = seg.get(key)
    if not isinstance(v, list) or len(v) != n or not all(
            isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)
            for x in v):
        raise MapFormatError(f"{where}.{key}: expected {n} finite numbers, got {v!r:.60}")
    return np.array(v, dtype=float)


def _mv(d, where: str) -> np.ndarray:
    if not isinstance(d, dict):
        raise MapFormatError(f"{where}: expected an object of blade coefficients")
    v = np.zeros(len(BLADE_NAMES))
    for k, x in d.items():
        if k not in BLADE_NAMES:
            raise MapFormatError(f"{where}: unknown blade {k!r}")
        if not isinstance(x, int | float) or isinstance(x, bool) or not math.isfinite(x):
            raise MapFormatError(f"{where}.{k}: not a finite number")
        v[BLADE_NAMES.index(k)] = x
    return v


def map_from_json(doc, source: str = "<map>") -> LineMap:
    if not isinstance(doc, dict):
        raise MapFormatError(f"{source}: not a JSON object")
    if doc.get("format") != FORMAT:
        raise MapFormatError(f"{source}: format is {doc.get('format')!r}, expected {FORMAT!r}")
    ver = doc.get("version")
    if not isinstance(ver, int) or ver < 1 or ver > VERSION:
        raise MapFormatError(f"{source}: unsupported version {ver!r} (this build reads "
                             f"1..{VERSION})")
    meta = doc.get("metadata", {})
    if not isinstance(meta, dict):
        raise MapFormatError(f"{source}: metadata must be an object")
    segs = doc.get("segments")
    if not isinstance(segs, list):
        raise MapFormatError(f"{source}: segments must be a list")
    m = len(segs)
    a, b = np.zeros((m, 2)), np.zeros((m, 2))
    cen, sc = np.zeros((m, 2)), np.zeros((m, 2, 2))
    n_obs, n_pts = np.zeros(m, int), np.zeros(m)
    pp = np.zeros((m, len(BLADE_NAMES)))
    for i, s in enumerate(segs):
        w = f"{source}: segments[{i}]"
        if not isinstance(s, dict):
            raise MapFormatError(f"{w}: not an object")
        a[i], b[i] = _vec(s, "a", 2, w), _vec(s, "b", 2, w)
        if np.linalg.norm(b[i] - a[i]) < 1e-6:
            raise MapFormatError(f"{w}: end points coincide")
        k = s.get("n_obs")
        if not isinstance(k, int) or isinstance(k, bool) or k < 1:
            raise MapFormatError(f"{w}.n_obs: expected a positive integer, got {k!r}")
        n_obs[i] = k
        npts = s.get("n_points", 2)
        if not isinstance(npts, int | float) or not math.isfinite(npts) or npts < 0:
            raise MapFormatError(f"{w}.n_points: expected a number >= 0")
        n_pts[i] = npts
        cen[i] = _vec(s, "centroid", 2, w) if "centroid" in s else 0.5 * (a[i] + b[i])
        if "scatter" in s:
            sxx, sxy, syy = _vec(s, "scatter", 3, w)
            sc[i] = [[sxx, sxy], [sxy, syy]]
        cga = s.get("cga")
        if cga is not None:
            if not isinstance(cga, dict) or "point_pair" not in cga:
                raise MapFormatError(f"{w}.cga: expected an object with point_pair")
            pp[i] = _mv(cga["point_pair"], f"{w}.cga.point_pair")
    if m and np.any(pp != 0):
        # the stored point pairs must be the end points' (scale-free comparison)
        ref = cga_segments(Segments(a, b, np.ones(m, int), np.zeros(m), cen, sc,
                                    np.zeros((m, 2, 2)))).pairs.v
        has = np.any(pp != 0, axis=1)
        num = np.abs(np.einsum("ij,ij->i", pp, ref))
        den = np.linalg.norm(pp, axis=1) * np.linalg.norm(ref, axis=1)
        bad = has & (num < (1 - 1e-6) * den)
        if bad.any():
            i = int(np.nonzero(bad)[0][0])
            raise MapFormatError(f"{source}: segments[{i}].cga.point_pair does not match its "
                                 "end points")
    m_ = LineMap(a, b, n_pts, cen, sc, n_obs, np.zeros(m, int), np.zeros(m, int), dict(meta))
    return m_


def load_map(path: str | Path) -> LineMap:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise MapFormatError(f"{path}: cannot read ({exc.strerror})") from None
    except UnicodeDecodeError as exc:
        raise MapFormatError(f"{path}: not a JSON map (binary data at byte {exc.start})") \
            from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MapFormatError(f"{path}: not JSON (line {exc.lineno}: {exc.msg})") from None
    return map_from_json(doc, str(path))

