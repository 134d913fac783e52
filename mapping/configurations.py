"""Configurations of planes (PRL §7, figs. 8-12): corridor, stairway, doorway, workplace.

Relations between planes are read with the algebra of incidence: the meet of two planes is
their common line, and its direction vanishes when they are parallel, so ``|dir(P1 v P2)|``
(the sine of the angle between them, for unit planes) is the parallelism test; a plane is
vertical when its meet with the horizontal plane has a direction, horizontal when not.

Works on anything with ``normal``, ``rho`` and ``extent`` (an (k, 3) polygon in the plane):
``DetectedPlane`` and ``MapPlane`` both qualify. Frames have z up (global or robot base);
pass ``up`` for another frame (e.g. (0, -1, 0) for an OpenCV camera frame).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from cgamap.cga import (
    Multivector,
    line,
    line_direction_moment,
    line_point_direction,
    meet,
    plane_from_hesse,
    point_pair,
)


@dataclass
class Configuration:
    kind: str  # "corridor", "stairway", "doorway", "workplace"
    planes: list[int]  # indices into the plane list given
    entities: dict[str, Multivector] = field(default_factory=dict)  # CGA, OPNS
    params: dict = field(default_factory=dict)  # JSON-able measurements

    def to_dict(self) -> dict:
        return {"kind": self.kind, "planes": self.planes, "params": self.params,
                "entities": {k: np.round(v.v, 9).tolist() for k, v in self.entities.items()}}


@dataclass
class ConfigRules:
    angle_tol: float = np.radians(5.0)  # horizontal / vertical / parallel tolerance
    corridor_width: tuple[float, float] = (0.8, 4.0)
    min_wall_area: float = 0.5  # m^2
    min_floor_area: float = 0.5
    rise: tuple[float, float] = (0.10, 0.25)  # stair rise range, m
    rise_regularity: float = 0.03  # max deviation of a rise from the median rise, m
    min_treads: int = 3
    door_width: tuple[float, float] = (0.6, 2.5)
    coplanar_rho_tol: float = 0.05
    table_height: tuple[float, float] = (0.6, 1.1)
    table_area: tuple[float, float] = (0.15, 6.0)


class _View:
    """The planes' unit CGA forms and the measurements the rules need, computed once."""

    def __init__(self, planes, up, rules: ConfigRules):
        self.planes = list(planes)
        self.up = np.asarray(up, float) / np.linalg.norm(up)
        self.rules = rules
        self.n = np.array([np.asarray(p.normal, float) for p in self.planes]).reshape(-1, 3)
        self.rho = np.array([float(p.rho) for p in self.planes])
        self.cga = [plane_from_hesse(n, r) for n, r in zip(self.n, self.rho, strict=True)]
        self.horizontal_plane = plane_from_hesse(self.up, 0.0)
        sin_tol = np.sin(rules.angle_tol)
        # incidence: direction of the meet with a horizontal plane = sin(angle to horizontal)
        tilt = np.array([_meet_sine(P, self.horizontal_plane) for P in self.cga])
        self.is_horizontal = tilt < sin_tol
        self.is_vertical = np.abs(self.n @ self.up) < sin_tol
        self.extent = [np.asarray(p.extent, float) for p in self.planes]
        # centre of the corner rectangle (the hull's vertex mean leans towards curved edges)
        self.centroid = np.array([np.asarray(getattr(p, "corners", e), float).mean(axis=0)
                                  for p, e in zip(self.planes, self.extent, strict=True)]
                                 ).reshape(-1, 3)
        self.height = self.centroid @ self.up
        self.area = np.array([_area(e, n) for e, n in zip(self.extent, self.n, strict=True)])

    def floor(self) -> int | None:
        """The lowest horizontal plane of at least min_floor_area."""
        cand = np.flatnonzero(self.is_horizontal & (self.area >= self.rules.min_floor_area))
        return int(cand[np.argmin(self.height[cand])]) if len(cand) else None

    def parallel(self, i: int, j: int) -> bool:
        return _meet_sine(self.cga[i], self.cga[j]) < np.sin(self.rules.angle_tol)

    def span(self, i: int, axis: np.ndarray) -> tuple[float, float]:
        s = self.extent[i] @ axis
        return float(s.min()), float(s.max())


def _meet_sine(A: Multivector, B: Multivector) -> float:
    """|direction| of the meet of two unit planes: the sine of the angle between them."""
    d, _ = line_direction_moment(meet(A, B))
    return float(np.linalg.norm(d))


def _area(extent: np.ndarray, n: np.ndarray) -> float:
    if len(extent) < 3:
        return 0.0
    cross = np.cross(extent - extent[0], np.roll(extent, -1, axis=0) - extent[0]).sum(axis=0)
    return 0.5 * abs(float(cross @ n))


def _overlap(a: tuple[float, float], b: tuple[float, float]) -> float:
    return min(a[1], b[1]) - max(a[0], b[0])


# ---- corridor ------------------------------------------------------------------------------


def _parallel_wall_pairs(view: _View, walls: np.ndarray):
    """Pairs (i, j) of parallel walls with wall i's normal n and wall j written as n.x = dj."""
    for a in range(len(walls)):
        for b in range(a + 1, len(walls)):
            i, j = int(walls[a]), int(walls[b])
            if view.parallel(i, j):
                n = view.n[i]
                yield i, j, n, float(view.rho[j] * np.sign(n @ view.n[j]))


def find_corridors(view: _View) -> list[Configuration]:
    """Two parallel vertical planes 0.8-4 m apart, facing each other over a floor; the axis is
    the meet of the floor with the walls' mid-plane."""
    r = view.rules
    floor = view.floor()
    if floor is None:
        return []
    walls = np.flatnonzero(view.is_vertical & (view.area >= r.min_wall_area))
    out = []
    for i, j, n, dj in _parallel_wall_pairs(view, walls):
        di = float(view.rho[i])
        width = abs(di - dj)
        if not r.corridor_width[0] <= width <= r.corridor_width[1]:
            continue
        along = np.cross(n, view.up)
        along /= np.linalg.norm(along)
        if _overlap(view.span(i, along), view.span(j, along)) <= 0:
            continue  # the walls must face each other along the corridor
        lo, hi = sorted((di, dj))
        f_lo, f_hi = view.span(floor, n)
        if _overlap((f_lo, f_hi), (lo, hi)) < 0.5 * width:
            continue  # the floor lies between the walls
        mid = plane_from_hesse(n, 0.5 * (di + dj))
        axis = meet(view.cga[floor], mid)
        p, d = line_point_direction(axis)
        out.append(Configuration(
            "corridor", [i, j, floor],
            {"wall_a": view.cga[i], "wall_b": view.cga[j], "floor": view.cga[floor],
             "mid_plane": mid, "axis": axis},
            {"width": width, "axis_point": p.tolist(), "axis_direction": d.tolist(),
             "length": _overlap(view.span(i, along), view.span(j, along))}))
    return out


# ---- stairway ------------------------------------------------------------------------------


def find_stairways(view: _View) -> list[Configuration]:
    """>= min_treads horizontal planes stacked at a regular rise (each within rise_regularity
    of the median rise), advancing in one horizontal direction, with the vertical risers
    between them."""
    r = view.rules
    hz = np.flatnonzero(view.is_horizontal)
    if len(hz) < r.min_treads:
        return []
    order = hz[np.argsort(view.height[hz])]
    # greedy chains over the height-sorted treads: next level is one rise up
    best: list[int] = []
    for start in range(len(order)):
        chain = [int(order[start])]
        for k in order[start + 1:]:
            dz = view.height[k] - view.height[chain[-1]]
            if r.rise[0] <= dz <= r.rise[1]:
                chain.append(int(k))
        if len(chain) > len(best):
            best = chain
    if len(best) < r.min_treads:
        return []
    rises = np.diff(view.height[best])
    rise = float(np.median(rises))
    if np.abs(rises - rise).max() > r.rise_regularity:
        return []
    # the treads' centroids advance along one horizontal direction
    c = view.centroid[best]
    flat = c - np.outer(c @ view.up, view.up)
    step = np.diff(flat, axis=0)
    direction = flat[-1] - flat[0]
    if np.linalg.norm(direction) < 1e-6 or np.any(step @ direction <= 0):
        return []
    direction /= np.linalg.norm(direction)
    going = float(np.median(step @ direction))
    # risers: vertical planes facing along the stair, their height span one rise
    risers = []
    for k in np.flatnonzero(view.is_vertical):
        if abs(view.n[k] @ direction) < np.cos(r.angle_tol):
            continue
        lo, hi = view.span(int(k), view.up)
        if abs((hi - lo) - rise) < 2 * r.rise_regularity + 0.02 and \
                view.height[best[0]] - 0.05 <= lo <= view.height[best[-1]] + 0.05:
            risers.append(int(k))
    if risers:  # the risers' normals give the walking direction more precisely
        rn = view.n[risers] * np.sign(view.n[risers] @ direction)[:, None]
        rn = rn.mean(axis=0) - (rn.mean(axis=0) @ view.up) * view.up
        direction = rn / np.linalg.norm(rn)
        going = float(np.median(step @ direction))
    ents = {f"tread_{i}": view.cga[k] for i, k in enumerate(best)}
    ents.update({f"riser_{i}": view.cga[k] for i, k in enumerate(risers)})
    ents["pitch_line"] = line(c[0], c[-1])
    return [Configuration("stairway", best + risers, ents,
                          {"treads": len(best), "risers": len(risers), "rise": rise,
                           "going": going, "direction": direction.tolist(),
                           "pitch_deg": float(np.degrees(np.arctan2(rise, going)))})]


# ---- doorway / entry hall ------------------------------------------------------------------


def find_doorways(view: _View) -> list[Configuration]:
    """Two coplanar vertical wall patches with a door-sized gap between them; the gap's edges
    at floor level form a CGA point pair, and the doorway's centre line is vertical."""
    r = view.rules
    walls = np.flatnonzero(view.is_vertical & (view.area >= 0.2))
    floor = view.floor()
    floor_h = float(view.height[floor]) if floor is not None else float(
        min((view.span(int(k), view.up)[0] for k in walls), default=0.0))
    out = []
    for i, j, n, dj in _parallel_wall_pairs(view, walls):
        if abs(view.rho[i] - dj) > r.coplanar_rho_tol:
            continue
        along = np.cross(view.up, n)
        along /= np.linalg.norm(along)
        si, sj = view.span(i, along), view.span(j, along)
        (l_lo, l_hi), (r_lo, r_hi) = sorted((si, sj))
        gap = r_lo - l_hi
        if not r.door_width[0] <= gap <= r.door_width[1]:
            continue
        wall_plane = plane_from_hesse(n, 0.5 * (view.rho[i] + dj))
        base = n * (0.5 * (view.rho[i] + dj))
        base = base - np.dot(base, along) * along - np.dot(base, view.up) * view.up
        left = base + l_hi * along + floor_h * view.up
        right = base + r_lo * along + floor_h * view.up
        centre = 0.5 * (left + right)
        top = min(view.span(i, view.up)[1], view.span(j, view.up)[1])
        out.append(Configuration(
            "doorway", [i, j] + ([floor] if floor is not None else []),
            {"wall": wall_plane, "gap": point_pair(left, right),
             "centre_line": line(centre, centre + view.up)},
            {"width": float(gap), "centre": centre.tolist(),
             "height": float(top - floor_h)}))
    return out


# ---- table / workplace ---------------------------------------------------------------------


def find_workplaces(view: _View, exclude=frozenset()) -> list[Configuration]:
    """A horizontal plane 0.6-1.1 m above the floor (or above z = 0 without one), of table
    size and not a stair tread (``exclude``); its corners and height above the floor."""
    r = view.rules
    floor = view.floor()
    floor_h = float(view.height[floor]) if floor is not None else 0.0
    out = []
    for k in np.flatnonzero(view.is_horizontal):
        k = int(k)
        h = float(view.height[k]) - floor_h
        if k == floor or k in exclude or not r.table_height[0] <= h <= r.table_height[1]:
            continue
        if not r.table_area[0] <= view.area[k] <= r.table_area[1]:
            continue
        corners = np.asarray(getattr(view.planes[k], "corners", view.extent[k]))
        ents = {"table": view.cga[k]}
        if floor is not None:
            ents["floor"] = view.cga[floor]
        out.append(Configuration("workplace", [k] + ([floor] if floor is not None else []),
                                 ents, {"height": h, "area": float(view.area[k]),
                                        "corners": np.round(corners, 4).tolist()}))
    return out


FINDERS = {"corridor": find_corridors, "stairway": find_stairways,
           "doorway": find_doorways, "workplace": find_workplaces}


def find_configurations(planes, up=(0.0, 0.0, 1.0), rules: ConfigRules | None = None,
                        kinds=tuple(FINDERS)) -> list[Configuration]:
    """All configurations of the given kinds among the planes."""
    view = _View(planes, up, rules or ConfigRules())
    if not view.planes:
        return []
    out: list[Configuration] = []
    treads: set[int] = set()
    for kind in sorted(kinds, key=lambda k: k != "stairway"):  # stairs first: treads known
        if kind == "workplace":
            out += find_workplaces(view, frozenset(treads))
            continue
        found = FINDERS[kind](view)
        if kind == "stairway":
            treads.update(i for c in found for i in c.planes)
        out += found
    return out
