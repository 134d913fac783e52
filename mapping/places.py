"""Place features from the 3D Hough space and place recognition (PRL §6, figs. 8-10).

A turn of the robot about z moves every plane's (theta, phi, rho) only in phi, by the same
angle (DESIGN.md); theta, rho and the differences of phi between planes stay. The feature
vector is made of those invariants only, as smooth fixed-length histograms so that nearest
neighbour search is a plain distance:

- a (theta, rho) density: each plane a Gaussian bump weighted by its support;
- a density of the wrap-aware phi differences |angle_diff(phi_i, phi_j)| (seed eq. 9) over
  pairs of non-horizontal planes (phi means nothing for a horizontal plane), weighted by the
  product of the pair's supports, with the pair's mean theta as a second axis.

Both parts are normalised to unit length; the distance of two places is the Euclidean
distance of their concatenations (0 identical, at most 2).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from cgamap.cga import angle_diff, hesse_to_hough3d

from .fileio import write_text_atomic


@dataclass
class FeatureSpec:
    theta_bins: int = 12
    rho_bins: int = 16
    rho_max: float = 8.0
    dphi_bins: int = 18
    sigma_theta: float = np.radians(8.0)
    sigma_rho: float = 0.35
    sigma_phi: float = np.radians(8.0)
    horizontal_tol: float = np.radians(10.0)  # theta this close to 0 or pi: no phi


def _hough_and_weight(planes) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) Hough points and (k,) weights (square root of the support -- inliers, else
    area -- so one huge floor does not drown the walls) of planes, or of
    (theta, phi, rho[, weight]) rows."""
    rows = []
    for p in planes:
        if hasattr(p, "normal"):
            t, ph, r = hesse_to_hough3d(np.asarray(p.normal, float), float(p.rho))
            w = float(getattr(p, "inliers", 0) or getattr(p, "area", 1.0) or 1.0)
            rows.append((float(t), float(ph), float(r), w))
        else:
            q = tuple(float(v) for v in p)
            rows.append(q if len(q) == 4 else q + (1.0,))
    if not rows:
        return np.zeros((0, 3)), np.zeros(0)
    a = np.array(rows)
    return a[:, :3], np.sqrt(np.maximum(a[:, 3], 0.0))


def place_features(planes, spec: FeatureSpec | None = None) -> np.ndarray:
    """The rotation-invariant feature vector of a set of planes (seen from one place)."""
    s = spec or FeatureSpec()
    h, w = _hough_and_weight(planes)
    t_c = (np.arange(s.theta_bins) + 0.5) * np.pi / s.theta_bins
    r_c = (np.arange(s.rho_bins) + 0.5) * s.rho_max / s.rho_bins
    d_c = (np.arange(s.dphi_bins) + 0.5) * np.pi / s.dphi_bins
    f1 = np.zeros((s.theta_bins, s.rho_bins))
    f2 = np.zeros((s.theta_bins, s.dphi_bins))
    if len(h):
        # A plane through (or near) the sensor has no reliable side: n and -n are equally
        # likely from noise. Such a plane counts as both, with flip weight q -> 1/2 at rho 0.
        q = 0.5 * np.exp(-0.5 * (h[:, 2] / s.sigma_rho) ** 2)

        def bump(x, centres, sigma):
            return np.exp(-0.5 * ((x[:, None] - centres) / sigma) ** 2)

        gt = ((1 - q)[:, None] * bump(h[:, 0], t_c, s.sigma_theta)
              + q[:, None] * bump(np.pi - h[:, 0], t_c, s.sigma_theta))
        f1 = np.einsum("k,kt,kr->tr", w, gt, bump(h[:, 2], r_c, s.sigma_rho))
        sloped = np.flatnonzero((h[:, 0] > s.horizontal_tol) & (h[:, 0] < np.pi - s.horizontal_tol))
        if len(sloped) >= 2:
            i, j = np.triu_indices(len(sloped), k=1)
            a, b = sloped[i], sloped[j]
            dphi = np.abs(angle_diff(h[a, 1], h[b, 1]))
            odd = q[a] * (1 - q[b]) + q[b] * (1 - q[a])  # one of the two flipped: pi - dphi

            def fold(d):  # |dphi| lives on [0, pi]: mirror the kernel at both ends
                return (bump(d, d_c, s.sigma_phi) + bump(-d, d_c, s.sigma_phi)
                        + bump(2 * np.pi - d, d_c, s.sigma_phi))

            gd = (1 - odd)[:, None] * fold(dphi) + odd[:, None] * fold(np.pi - dphi)
            # second axis: the pair's mean slope |cos theta|, which a flip leaves alone
            slope = 0.5 * (np.abs(np.cos(h[a, 0])) + np.abs(np.cos(h[b, 0])))
            gtm = bump(np.arccos(slope), t_c, s.sigma_theta)
            f2 = np.einsum("p,pt,pd->td", w[a] * w[b], gtm, gd)
    parts = []
    for f in (f1.ravel(), f2.ravel()):
        n = np.linalg.norm(f)
        parts.append(f / n if n > 0 else f)
    return np.concatenate(parts)


@dataclass
class PlaceDatabase:
    """Stored places and nearest-neighbour recognition with a distance threshold."""

    threshold: float = 0.35
    spec: FeatureSpec = field(default_factory=FeatureSpec)
    names: list[str] = field(default_factory=list)
    features: list[np.ndarray] = field(default_factory=list)

    def add(self, name: str, planes) -> np.ndarray:
        f = place_features(planes, self.spec)
        self.names.append(name)
        self.features.append(f)
        return f

    def distances(self, planes) -> np.ndarray:
        if not self.features:
            return np.zeros(0)
        f = place_features(planes, self.spec)
        return np.linalg.norm(np.stack(self.features) - f, axis=1)

    def recognise(self, planes) -> tuple[str | None, float]:
        """(name of the nearest stored place, distance), or (None, distance) when even the
        nearest is farther than the threshold (a new place)."""
        d = self.distances(planes)
        if len(d) == 0:
            return None, float("inf")
        k = int(np.argmin(d))
        return (self.names[k] if d[k] <= self.threshold else None), float(d[k])

    def save(self, path: str | Path) -> None:
        write_text_atomic(path, json.dumps({
            "threshold": self.threshold, "spec": self.spec.__dict__,
            "places": [{"name": n, "features": f.tolist()}
                       for n, f in zip(self.names, self.features, strict=True)]}))

    @classmethod
    def load(cls, path: str | Path) -> PlaceDatabase:
        d = json.loads(Path(path).read_text())
        db = cls(threshold=d["threshold"], spec=FeatureSpec(**d["spec"]))
        for p in d["places"]:
            db.names.append(p["name"])
            db.features.append(np.asarray(p["features"], float))
        return db
