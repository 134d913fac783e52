"""The 3D plane map: planes merged across frames, virtual walls, exports (PLY, JSON, PNG).

Every map plane is kept as a CGA plane (OPNS, the dual of n + rho einf) with its bounding
polygon; observations from a new frame are moved to the global frame by the frame's motor
(X' = M X ~M, seed eq. 7, applied to the CGA plane and to its polygon) and merged with a map
plane when their Hough parameters agree and their extents touch or overlap. Segments of the
2D line map become *virtual walls* (seed 000 fig. 2): vertical quads up to a wall height.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from cgamap.cga import (
    Multivector,
    apply,
    apply_points,
    hesse_to_hough3d,
    plane,
    plane_from_hesse,
    plane_to_hesse,
)

from .fileio import write_text_atomic
from .matching import segment_distances
from .planes import hull_2d, lift_uv, min_rect_2d, to_plane_uv
from .render import write_image_atomic


@dataclass(eq=False)  # identity, not field-wise ==: fields are numpy arrays
class MapPlane:
    """A plane of the map: n.x = rho (rho >= 0) with its extent polygon in the plane."""

    normal: np.ndarray
    rho: float
    extent: np.ndarray  # (k, 3) convex polygon in the plane
    inliers: int = 0
    observations: int = 1
    kind: str = "plane"  # "plane" (seen by the camera) or "wall" (extruded 2D segment)
    id: int = -1
    corners: np.ndarray = field(default=None)  # (4, 3); derived from extent when None

    def __post_init__(self):
        self.normal = np.asarray(self.normal, dtype=float)
        self.extent = np.asarray(self.extent, dtype=float)
        if self.corners is None:
            self.corners = _min_rect(self.extent, self.normal, self.rho)

    @property
    def hough(self) -> tuple[float, float, float]:
        t, p, r = hesse_to_hough3d(self.normal, self.rho)
        return float(t), float(p), float(r)

    @property
    def centroid(self) -> np.ndarray:
        return self.extent.mean(axis=0)

    @property
    def area(self) -> float:
        return _polygon_area(to_plane_uv(self.extent, self.normal))

    def cga(self) -> Multivector:
        return plane_from_hesse(self.normal, self.rho)

    def to_dict(self) -> dict:
        t, p, r = self.hough
        return {
            "id": self.id, "kind": self.kind,
            "normal": [round(float(v), 6) for v in self.normal], "rho": round(self.rho, 6),
            "hough": {"theta": round(t, 6), "phi": round(p, 6), "rho": round(r, 6)},
            "inliers": int(self.inliers), "observations": int(self.observations),
            "area": round(self.area, 4),
            "corners": np.round(self.corners, 5).tolist(),
            "extent": np.round(self.extent, 5).tolist(),
            "cga": np.round(self.cga().v, 9).tolist(),
        }


# ---- polygon helpers (in the plane's own 2D basis) -----------------------------------------


def _polygon_area(uv: np.ndarray) -> float:
    x, y = uv[:, 0], uv[:, 1]
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _min_rect(extent: np.ndarray, normal: np.ndarray, rho: float) -> np.ndarray:
    return lift_uv(min_rect_2d(to_plane_uv(extent, normal)), normal, rho)


def polygon_gap(poly_a: np.ndarray, poly_b: np.ndarray) -> float:
    """0 when two convex 2D polygons overlap, else the distance between their boundaries."""
    a32, b32 = poly_a.astype(np.float32), poly_b.astype(np.float32)
    if len(a32) >= 3 and len(b32) >= 3:
        area, _ = cv2.intersectConvexConvex(a32, b32)
        if area > 0:
            return 0.0
    ea, eb = np.roll(poly_a, -1, axis=0), np.roll(poly_b, -1, axis=0)
    return float(min(segment_distances(poly_a, poly_b, eb).min(),
                     segment_distances(poly_b, poly_a, ea).min()))


# ---- the map -------------------------------------------------------------------------------


@dataclass
class MergeRule:
    angle_tol: float = np.radians(5.0)  # normals agree within this
    rho_tol: float = 0.10  # m; Hesse distances agree within this
    gap: float = 0.30  # m; extents closer than this (in the plane) are one surface


class PlaneMap:
    """Planes merged across frames and virtual walls, all as CGA entities."""

    def __init__(self, rule: MergeRule | None = None):
        self.rule = rule or MergeRule()
        self.planes: list[MapPlane] = []
        self._next_id = 0

    # -- adding ------------------------------------------------------------------------------

    def add_planes(self, planes, motor: Multivector | None = None) -> list[int]:
        """Add detected planes (anything with normal, rho, extent, inliers) seen from a frame
        whose pose is ``motor`` (frame -> global; None: already global). Returns map ids."""
        ids = []
        for p in planes:
            n, rho, extent = np.asarray(p.normal, float), float(p.rho), np.asarray(p.extent)
            if motor is not None:
                n, rho = plane_to_hesse(apply(motor, plane_from_hesse(n, rho)))
                n, rho = np.asarray(n, float), float(rho)
                extent = apply_points(motor, extent)
            ids.append(self._merge(MapPlane(n, rho, extent, inliers=int(getattr(p, "inliers", 0)),
                                            kind=getattr(p, "kind", "plane"))))
        return ids

    def add_virtual_walls(self, segments: np.ndarray, height: float = 2.5,
                          floor_z: float = 0.0) -> list[int]:
        """Extrude 2D segments ((n, 2, 2) end points, global frame) to vertical walls of
        ``height`` above ``floor_z`` (seed 000 fig. 2). The CGA plane of each wall is the
        join a ^ b ^ c ^ einf of two foot points and one head point."""
        seg = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
        if len(seg) == 0:
            return []
        z0 = np.full((len(seg), 1), float(floor_z))
        a = np.hstack([seg[:, 0], z0])
        b = np.hstack([seg[:, 1], z0])
        head = np.array([0.0, 0.0, height])
        P = plane(a, b, a + head)
        normals, rhos = plane_to_hesse(P)
        ids = []
        for i in range(len(seg)):
            quad = np.stack([a[i], b[i], b[i] + head, a[i] + head])
            ids.append(self._add(MapPlane(normals[i], float(rhos[i]), quad, kind="wall",
                                          corners=quad)))
        return ids

    def _add(self, mp: MapPlane) -> int:
        mp.id = self._next_id
        self._next_id += 1
        self.planes.append(mp)
        return mp.id

    def same_surface(self, a: MapPlane, b: MapPlane) -> bool:
        """Same plane: Hough parameters agree and the extents touch or overlap."""
        if a.kind != b.kind:
            return False
        cos = float(a.normal @ b.normal)
        if abs(cos) < np.cos(self.rule.angle_tol):
            return False
        rho_b = b.rho if cos > 0 else -b.rho
        if abs(a.rho - rho_b) > self.rule.rho_tol:
            return False
        pa = to_plane_uv(a.extent, a.normal)
        pb = to_plane_uv(b.extent, a.normal)
        return polygon_gap(hull_2d(pa), hull_2d(pb)) <= self.rule.gap

    def _merge(self, obs: MapPlane) -> int:
        for mp in self.planes:
            if self.same_surface(mp, obs):
                self._absorb(mp, obs)
                # absorbing can make it touch another map plane: fold those in too
                folded = [q for q in self.planes if q is not mp and self.same_surface(mp, q)]
                for other in folded:
                    self._absorb(mp, other)
                self.planes = [q for q in self.planes if not any(q is f for f in folded)]
                return mp.id
        return self._add(obs)

    @staticmethod
    def _absorb(mp: MapPlane, obs: MapPlane) -> None:
        """Support-weighted mean of the Hesse forms; extent: hull of both, in the new plane."""
        sign = 1.0 if float(mp.normal @ obs.normal) >= 0 else -1.0
        wa, wb = max(mp.inliers, 1), max(obs.inliers, 1)
        n = wa * mp.normal + wb * sign * obs.normal
        rho = (wa * mp.rho + wb * sign * obs.rho) / (wa + wb)
        norm = np.linalg.norm(n)
        n, rho = n / norm, rho * (wa + wb) / norm
        if rho < 0:
            n, rho = -n, -rho
        pts = np.concatenate([mp.extent, obs.extent])
        uv = hull_2d(to_plane_uv(pts, n))
        mp.normal, mp.rho = n, float(rho)
        mp.extent = lift_uv(uv, n, rho)
        mp.corners = _min_rect(mp.extent, n, rho)
        mp.inliers = mp.inliers + obs.inliers
        mp.observations += obs.observations

    # -- the daemon's interface (drop-in for daemon/loop.py's PlaneMap) ----------------------

    def integrate(self, planes, motor: Multivector | None = None) -> int:
        """Add a frame's planes; returns how many were added or merged."""
        return len(self.add_planes(planes, motor))

    def as_list(self) -> list[dict]:
        """The planes as JSON-able dicts (normal, rho, hough, corners, extent, cga, ...)."""
        return [{**p.to_dict(), "seen": p.observations} for p in self.planes]

    def state(self) -> dict:
        return self.to_dict()

    def load_state(self, st: dict) -> None:
        other = PlaneMap.from_dict(st)
        self.rule, self.planes, self._next_id = other.rule, other.planes, other._next_id

    # -- exports -----------------------------------------------------------------------------

    def to_dict(self) -> dict:
        return {"planes": [p.to_dict() for p in self.planes],
                "merge_rule": {"angle_tol": self.rule.angle_tol, "rho_tol": self.rule.rho_tol,
                               "gap": self.rule.gap}}

    @classmethod
    def from_dict(cls, d: dict) -> PlaneMap:
        """Rebuild a map written by ``to_dict`` (checkpoints, JSON exports)."""
        rule = MergeRule(**d.get("merge_rule", {}))
        pm = cls(rule)
        for q in d.get("planes", []):
            mp = MapPlane(np.asarray(q["normal"], float), float(q["rho"]),
                          np.asarray(q["extent"], float), inliers=int(q.get("inliers", 0)),
                          observations=int(q.get("observations", 1)),
                          kind=q.get("kind", "plane"), id=int(q.get("id", -1)),
                          corners=np.asarray(q["corners"], float) if "corners" in q else None)
            pm.planes.append(mp)
        pm._next_id = max((p.id for p in pm.planes), default=-1) + 1
        return pm

    def save_json(self, path: str | Path) -> None:
        write_text_atomic(path, json.dumps(self.to_dict(), indent=1))

    def save_ply(self, path: str | Path) -> None:
        """ascii PLY: four corner vertices and one quad face per plane, coloured by kind."""
        colours = {"plane": (70, 130, 220), "wall": (200, 200, 200)}
        lines = []
        for p in self.planes:
            r, g, b = colours.get(p.kind, (255, 0, 0))
            lines += [f"{x:.5f} {y:.5f} {z:.5f} {r} {g} {b}" for x, y, z in p.corners]
        faces = [f"4 {4 * i} {4 * i + 1} {4 * i + 2} {4 * i + 3}" for i in range(len(self.planes))]
        head = ["ply", "format ascii 1.0", "comment cgamap plane map",
                f"element vertex {4 * len(self.planes)}", "property float x", "property float y",
                "property float z", "property uchar red", "property uchar green",
                "property uchar blue", f"element face {len(self.planes)}",
                "property list uchar int vertex_indices", "end_header"]
        write_text_atomic(path, "\n".join(head + lines + faces) + "\n")

    def hough_image(self, size: tuple[int, int] = (720, 400)) -> np.ndarray:
        return hough_space_image(self.planes, size)

    def save_hough_png(self, path: str | Path, size: tuple[int, int] = (720, 400)) -> None:
        """The Hough-space picture, encoded in memory and written atomically: a failed write
        leaves the previous picture whole."""
        write_image_atomic(path, self.hough_image(size), "PNG")


def hough_space_image(planes, size: tuple[int, int] = (720, 400),
                      rho_max: float | None = None) -> np.ndarray:
    """The PRL figures' view of the 3D Hough space: a theta-phi scatter (phi across, theta
    down), one disc per plane, coloured by rho (colour bar on the right), sized by support."""
    w, h = size
    margin, bar = 40, 50
    img = np.full((h, w, 3), 255, np.uint8)
    pw, ph = w - 2 * margin - bar, h - 2 * margin
    cv2.rectangle(img, (margin, margin), (margin + pw, margin + ph), (0, 0, 0), 1)
    for k in range(5):  # grid and tick labels every 90 deg of phi, 45 deg of theta
        x = margin + int(k * pw / 4)
        cv2.line(img, (x, margin), (x, margin + ph), (220, 220, 220), 1)
        cv2.putText(img, f"{-180 + 90 * k}", (x - 12, margin + ph + 15),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        y = margin + int(k * ph / 4)
        cv2.line(img, (margin, y), (margin + pw, y), (220, 220, 220), 1)
        cv2.putText(img, f"{45 * k}", (5, y + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    cv2.putText(img, "phi (deg)", (margin + pw // 2 - 25, h - 8), cv2.FONT_HERSHEY_SIMPLEX,
                0.4, (0, 0, 0), 1)
    cv2.putText(img, "theta", (2, margin - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
    planes = list(planes)
    hough = np.array([p.hough for p in planes]).reshape(-1, 3)
    rmax = rho_max or (float(hough[:, 2].max()) if len(hough) else 1.0) or 1.0
    ramp = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_VIRIDIS)
    bx = margin + pw + 15
    for i in range(ph):  # colour bar, rho grows upwards
        cv2.line(img, (bx, margin + ph - i), (bx + 12, margin + ph - i),
                 tuple(int(c) for c in ramp[int(255 * i / max(ph - 1, 1)), 0]), 1)
    cv2.putText(img, f"{rmax:.1f}m", (bx - 5, margin - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                (0, 0, 0), 1)
    cv2.putText(img, "0", (bx, margin + ph + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    support = np.array([max(getattr(p, "inliers", 1), 1) for p in planes], float)
    radius = 3 + 3 * np.log10(support) if len(support) else support
    for (t, p, r), rad in zip(hough, radius, strict=True):
        x = margin + int(round((p + np.pi) / (2 * np.pi) * pw))
        y = margin + int(round(t / np.pi * ph))
        colour = tuple(int(c) for c in ramp[int(np.clip(r / rmax, 0, 1) * 255), 0])
        cv2.circle(img, (x, y), int(rad), colour, -1, cv2.LINE_AA)
        cv2.circle(img, (x, y), int(rad), (0, 0, 0), 1, cv2.LINE_AA)
    return img
