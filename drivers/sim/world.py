"""The simulated 2D world the laser twins sense: walls as segments, a trajectory, a noise model.

Sensor-agnostic: :meth:`World.raycast` answers "how far along these rays is the first wall"
for any ray fan; the twins encode the answer in their own wire format.  Walls are records with
a base height and a height (``Wall.z0``, ``Wall.height``) so 3D renderers can extrude them;
the 2D ray cast ignores heights.

Things that move (:class:`Mover`: people, carts) are boxes that walk a route and stand at
its stops; :meth:`World.scan` at time t sees them where they are then.

Coordinates: metres, world frame x/y, headings counter-clockwise from +x (radians).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Wall:
    """A wall segment from (x0, y0) to (x1, y1), standing from ``z0`` to ``z0 + height``."""

    x0: float
    y0: float
    x1: float
    y1: float
    height: float = 2.5
    z0: float = 0.0
    kind: str = "wall"  # "wall", "furniture", ... (renderers may colour by it)


@dataclass(frozen=True)
class Mover:
    """A box ``size`` (length along its way, width) that walks the closed ``route`` of
    stops at ``speed`` and stands ``pause`` seconds at each: a person (about 0.3 x 0.5 m at
    the height of a laser that sees the torso, standing to look at a booth), or a cart
    parked for minutes.  ``phase`` seconds of its cycle have passed at t = 0."""

    route: tuple[tuple[float, float], ...]
    speed: float = 1.0
    pause: float = 0.0
    phase: float = 0.0
    size: tuple[float, float] = (0.3, 0.5)

    def pose(self, t: float) -> tuple[float, float, float]:
        """(x, y, heading) at time ``t``: on the way between two stops, or standing at one
        (facing the way it came)."""
        p = np.asarray(self.route, dtype=float)
        q = np.roll(p, -1, axis=0)
        length = np.hypot(*(q - p).T)
        walk = length / self.speed
        cycle = float(np.sum(walk) + self.pause * len(p))
        if cycle <= 0.0:
            return float(p[0, 0]), float(p[0, 1]), 0.0
        u = (t + self.phase) % cycle
        for i in range(len(p)):  # a handful of stops
            heading = float(np.arctan2(q[i, 1] - p[i, 1], q[i, 0] - p[i, 0]))
            if u < walk[i]:
                f = u / walk[i]
                x, y = p[i] + f * (q[i] - p[i])
                return float(x), float(y), heading
            u -= walk[i]
            if u < self.pause:
                return float(q[i, 0]), float(q[i, 1]), heading
            u -= self.pause
        return float(p[0, 0]), float(p[0, 1]), 0.0

    def edges(self, t: float) -> np.ndarray:
        """(4, 4) the box's sides at time ``t`` as x0, y0, x1, y1."""
        x, y, h = self.pose(t)
        c, s = np.cos(h), np.sin(h)
        hl, hw = self.size[0] / 2.0, self.size[1] / 2.0
        corners = np.array([[x + c * u - s * v, y + s * u + c * v]
                            for u, v in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))])
        return np.hstack([corners, np.roll(corners, -1, axis=0)])


@dataclass
class NoiseModel:
    """Range noise of a simulated sensor.

    ``sigma`` (m) Gaussian noise on every return; ``sigma_rel`` adds noise proportional to the
    range; ``dropout`` is the probability that a beam returns nothing (NaN).
    """

    sigma: float = 0.01
    sigma_rel: float = 0.0
    dropout: float = 0.0

    def apply(self, ranges: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Noisy copy of ``ranges``: no-return (inf/NaN) beams and dropouts come out NaN."""
        r = np.asarray(ranges, dtype=float)
        finite = np.isfinite(r)
        scale = self.sigma + self.sigma_rel * np.where(finite, np.abs(r), 0.0)
        out = np.where(finite, r + rng.normal(0.0, 1.0, r.shape) * scale, np.nan)
        out = np.maximum(out, 0.0)
        if self.dropout > 0:
            out[rng.random(r.shape) < self.dropout] = np.nan
        return out


def _centripetal(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray, p3: np.ndarray,
                 u: np.ndarray) -> np.ndarray:
    """Centripetal Catmull-Rom (alpha = 1/2) between p1 and p2 at fractions u (no cusps or
    self-intersections, unlike the uniform form with unevenly spaced waypoints)."""
    t1 = np.linalg.norm(p1 - p0) ** 0.5
    t2 = t1 + np.linalg.norm(p2 - p1) ** 0.5
    t3 = t2 + np.linalg.norm(p3 - p2) ** 0.5
    t = t1 + u * (t2 - t1)
    a1 = ((t1 - t) * p0 + t * p1) / t1
    a2 = ((t2 - t) * p1 + (t - t1) * p2) / (t2 - t1)
    a3 = ((t3 - t) * p2 + (t - t2) * p3) / (t3 - t2)
    b1 = ((t2 - t) * a1 + t * a2) / t2
    b2 = ((t3 - t) * a2 + (t - t1) * a3) / (t3 - t1)
    return ((t2 - t) * b1 + (t - t1) * b2) / (t2 - t1)


def _rect(x0: float, y0: float, x1: float, y1: float, **kw) -> list[Wall]:
    return [Wall(x0, y0, x1, y0, **kw), Wall(x1, y0, x1, y1, **kw),
            Wall(x1, y1, x0, y1, **kw), Wall(x0, y1, x0, y0, **kw)]


def _polyline(points: list[tuple[float, float]], closed: bool = False, **kw) -> list[Wall]:
    pts = list(points) + ([points[0]] if closed else [])
    return [Wall(a[0], a[1], b[0], b[1], **kw) for a, b in zip(pts[:-1], pts[1:], strict=True)]


@dataclass
class World:
    """Walls plus a closed, smooth, deterministic path through them."""

    name: str
    walls: list[Wall]
    waypoints: np.ndarray          # (k, 2) closed loop the trajectory passes through
    speed: float = 0.5             # m/s along the path
    movers: list[Mover] = field(default_factory=list)  # people and carts (not in the map)
    _path: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    @property
    def segments(self) -> np.ndarray:
        """(n, 4) array of x0, y0, x1, y1."""
        return np.array([[w.x0, w.y0, w.x1, w.y1] for w in self.walls], dtype=float)

    @property
    def heights(self) -> np.ndarray:
        """(n, 2) array of z0 and height per wall, in the order of :attr:`segments`."""
        return np.array([[w.z0, w.height] for w in self.walls], dtype=float)

    def bounds(self) -> tuple[float, float, float, float]:
        s = self.segments
        xs, ys = s[:, [0, 2]], s[:, [1, 3]]
        return float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())

    def movers_at(self, t: float) -> np.ndarray:
        """(4k, 4) the movers' sides at time ``t`` (x0, y0, x1, y1)."""
        if not self.movers:
            return np.zeros((0, 4))
        return np.vstack([m.edges(t) for m in self.movers])

    def raycast(self, x: float, y: float, theta: float, angles: np.ndarray,
                max_range: float = np.inf, t: float | None = None) -> np.ndarray:
        """Distance to the first wall along each beam at ``theta + angles`` from (x, y); with
        a time ``t``, to the first wall or mover there then.

        Vectorised over beams × walls.  Beams that hit nothing within ``max_range`` give inf.
        """
        seg = self.segments
        if t is not None and self.movers:
            seg = np.vstack([seg, self.movers_at(t)])
        a = theta + np.asarray(angles, dtype=float)
        d = np.stack([np.cos(a), np.sin(a)], axis=-1)[:, None, :]        # (m, 1, 2)
        p0 = seg[None, :, 0:2]                                              # (1, n, 2)
        e = seg[None, :, 2:4] - p0                                          # (1, n, 2)
        w = p0 - np.array([x, y])                                           # (1, n, 2)
        denom = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]               # (m, n)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / denom     # along the ray
            s = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / denom     # along the wall
        hit = (np.abs(denom) > 1e-12) & (t > 1e-9) & (s >= 0.0) & (s <= 1.0)
        t = np.where(hit, t, np.inf)
        r = t.min(axis=1) if t.shape[1] else np.full(len(a), np.inf)
        r[r > max_range] = np.inf
        return r

    def scan(self, t: float, angles: np.ndarray, max_range: float,
             noise: NoiseModel | None, rng: np.random.Generator,
             mount: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
        """Ranges of a sensor mounted at ``mount`` (x, y, yaw in the robot frame) at time t;
        no-return beams NaN once noise is applied, inf without a noise model."""
        x, y, th = self.trajectory(t)
        c, s = np.cos(th), np.sin(th)
        sx, sy = x + c * mount[0] - s * mount[1], y + s * mount[0] + c * mount[1]
        r = self.raycast(sx, sy, th + mount[2], angles, max_range, t)
        return noise.apply(r, rng) if noise is not None else r

    # -- trajectory ------------------------------------------------------------------------
    def _dense_path(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closed centripetal Catmull-Rom spline through the waypoints, densely sampled."""
        if self._path is None:
            p = np.asarray(self.waypoints, dtype=float)
            k = len(p)
            u = np.linspace(0.0, 1.0, 200, endpoint=False)[:, None]
            chunks = []
            for i in range(k):  # loop over waypoints (a handful), vectorised over samples
                chunks.append(_centripetal(p[(i - 1) % k], p[i], p[(i + 1) % k],
                                           p[(i + 2) % k], u))
            pts = np.concatenate(chunks + [p[:1]])                          # closed
            step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
            s = np.concatenate([[0.0], np.cumsum(step)])
            dx = np.gradient(pts[:, 0], s, edge_order=1)
            dy = np.gradient(pts[:, 1], s, edge_order=1)
            # the closing point duplicates the first: use the true tangent there too
            dx[-1], dy[-1] = dx[0], dy[0]
            heading = np.unwrap(np.arctan2(dy, dx))
            self._path = (s, pts, heading)
        return self._path

    @property
    def path_length(self) -> float:
        return float(self._dense_path()[0][-1])

    def trajectory(self, t: float | np.ndarray) -> tuple:
        """Pose (x, y, theta) of the robot at time ``t`` seconds (scalars or arrays).

        The robot drives the closed path at ``speed``; theta wraps into (-pi, pi].
        """
        s, pts, heading = self._dense_path()
        total = s[-1]
        turns = np.floor_divide(np.asarray(t, dtype=float) * self.speed, total)
        q = np.mod(np.asarray(t, dtype=float) * self.speed, total)
        x = np.interp(q, s, pts[:, 0])
        y = np.interp(q, s, pts[:, 1])
        th = np.interp(q, s, heading) + turns * (heading[-1] - heading[0])
        th = np.angle(np.exp(1j * th))
        if np.ndim(t) == 0:
            return float(x), float(y), float(th)
        return x, y, th


def _corridor() -> World:
    # 20 m x 2 m corridor with two door niches and a pillar, closed at both ends.
    walls = _polyline([(0, -1), (6, -1), (6, -1.8), (7, -1.8), (7, -1), (20, -1),
                       (20, 1), (13, 1), (13, 1.8), (14.2, 1.8), (14.2, 1), (0, 1)], closed=True)
    walls += _rect(9.8, 0.6, 10.2, 1.0, kind="pillar")
    way = np.array([[1.5, -0.5], [10.0, -0.5], [17.8, -0.5], [18.3, 0.0], [17.8, 0.5],
                    [13.0, 0.4], [10.0, 0.1], [7.0, 0.4], [1.5, 0.5], [1.0, 0.0]])
    return World("corridor", walls, way, speed=0.6)


def _room() -> World:
    # 8 m x 6 m room; a table, a cabinet against a wall, a pillar, a box.
    walls = _rect(0.0, 0.0, 8.0, 6.0)
    walls += _rect(3.0, 2.4, 4.6, 3.4, kind="furniture", height=0.75)   # table
    walls += _rect(6.8, 4.0, 8.0, 5.2, kind="furniture", height=1.8)    # cabinet
    walls += _rect(1.2, 4.4, 1.6, 4.8, kind="pillar")
    walls += _rect(5.5, 0.0, 6.4, 0.7, kind="furniture", height=0.6)    # box
    way = np.array([[1.2, 1.2], [4.0, 1.1], [6.8, 1.5], [6.8, 3.2], [5.6, 4.8],
                    [3.2, 4.8], [0.9, 3.4]])
    return World("room", walls, way, speed=0.4)


def _loop() -> World:
    # A square loop of 2 m wide corridors around a 12 m x 8 m block, with a side alcove.
    walls = _polyline([(0, 0), (16, 0), (16, 12), (0, 12)], closed=True)
    walls += _rect(2.0, 2.0, 14.0, 10.0)
    walls = [w for w in walls if not (w.x0 == 16 and w.x1 == 16)]
    walls += _polyline([(16, 0), (16, 5), (17.5, 5), (17.5, 7), (16, 7), (16, 12)])
    way = np.array([[1.0, 1.0], [8.0, 1.0], [15.0, 1.0], [15.0, 6.0], [15.0, 11.0],
                    [8.0, 11.0], [1.0, 11.0], [1.0, 6.0]])
    return World("loop", walls, way, speed=0.8)


def _octagon(cx: float, cy: float, r: float, **kw) -> list[Wall]:
    a = np.linspace(0.0, 2.0 * np.pi, 9)[:-1]
    return _polyline([(cx + r * np.cos(t), cy + r * np.sin(t)) for t in a], closed=True, **kw)


def _hall() -> World:
    # A 60 m x 36 m exhibition hall: two rows of pillars, booths; most walls beyond 25 m.
    walls = _rect(0.0, 0.0, 60.0, 36.0)
    for x in range(10, 60, 10):
        for y in (12.0, 24.0):
            walls += _rect(x - 0.4, y - 0.4, x + 0.4, y + 0.4, kind="pillar")
    for x, y in [(8, 4), (20, 6), (33, 3), (45, 7), (12, 26.5), (38, 26.5), (48, 33.5)]:
        walls += _rect(x, y, x + 3.0, y + 2.0, kind="furniture", height=2.0)  # booths
    way = np.array([[4, 18], [30, 18], [56, 18], [56, 31], [30, 31], [4, 31]], float)
    return World("hall", walls, way, speed=0.5)


def _expo() -> World:
    # The hall during a fair: 24 visitors walk between booths and stand at each for up to a
    # minute, and 4 carts are parked for three minutes at a time, then moved on: in a lap
    # of the robot's (4.5 min) a cart stands where the last lap saw floor.
    w = _hall()
    rng = np.random.default_rng(5)
    inner = np.array([[v.x0, v.y0, v.x1, v.y1] for v in w.walls if v.kind != "wall"])
    way = w._dense_path()[1]

    def gap(p: np.ndarray, seg: np.ndarray) -> float:
        # point to segments (drivers import nothing of mapping, where this lives as
        # matching.segment_distances)
        d = seg[:, 2:] - seg[:, :2]
        t = np.clip(np.einsum("kx,kx->k", p - seg[:, :2], d) / np.einsum("kx,kx->k", d, d),
                    0.0, 1.0)
        return float(np.hypot(*(p - seg[:, :2] - t[:, None] * d).T).min())

    def stop(clear: float) -> tuple[float, float]:
        while True:  # off the robot's way, clear of (and not inside) the booths and pillars
            p = rng.uniform((3.0, 3.0), (57.0, 33.0))
            if (np.hypot(*(way - p).T).min() >= clear and gap(p, inner) > 1.2):
                return float(p[0]), float(p[1])

    for _ in range(24):
        w.movers.append(Mover(tuple(stop(1.5) for _ in range(4)), speed=rng.uniform(0.6, 1.2),
                              pause=rng.uniform(10.0, 60.0), phase=rng.uniform(0.0, 300.0)))
    for _ in range(4):
        w.movers.append(Mover(tuple(stop(2.5) for _ in range(3)), speed=0.8, pause=180.0,
                              phase=rng.uniform(0.0, 600.0), size=(1.2, 0.8)))
    w.name = "expo"
    return w


def _campus() -> World:
    # Six buildings round a 75 m x 24 m quad with trees (a few beams each, no lines): the
    # facades are 10-40 m from the path.
    rng = np.random.default_rng(7)
    walls = []
    for box in [(-30, 25, 5, 40), (15, 25, 45, 38), (50, -20, 65, 30), (-30, -40, 0, -25),
                (10, -42, 45, -28), (-50, -20, -38, 15)]:
        walls += _rect(*map(float, box), height=10.0)
    for _ in range(40):
        x, y = rng.uniform(-35.0, 45.0), rng.uniform(-20.0, 18.0)
        if min(abs(y + 12), abs(y - 12)) > 2.5 and min(abs(x + 30), abs(x - 42)) > 2.5:
            walls += _octagon(x, y, rng.uniform(0.15, 0.4), kind="tree", height=4.0)
    way = np.array([[-30, -12], [5, -12], [42, -12], [42, 12], [5, 12], [-30, 12]], float)
    return World("campus", walls, way, speed=1.0)


def _recessed(p0, p1, normal, rng: np.random.Generator) -> list[Wall]:
    """A straight wall from p0 to p1 with door recesses 0.9-1.6 m wide and 0.15-0.5 m deep
    towards ``normal``, 2-9 m apart."""
    p0, p1, n = (np.asarray(v, float) for v in (p0, p1, normal))
    length = float(np.linalg.norm(p1 - p0))
    u = (p1 - p0) / length
    pts = [p0]
    x = rng.uniform(2.0, 5.0)
    while x < length - 4.0:
        w, d = rng.uniform(0.9, 1.6), rng.uniform(0.15, 0.5)
        a, b = p0 + u * x, p0 + u * (x + w)
        pts += [a, a + n * d, b + n * d, b]
        x += w + rng.uniform(2.0, 9.0)
    return _polyline([(float(q[0]), float(q[1])) for q in [*pts, p1]])


def _long_corridor() -> World:
    # A 150 m x 4 m corridor, doors (recesses) at irregular spacing on both sides, driven
    # there and back: along it only the recesses' sides fix the position.
    rng = np.random.default_rng(11)
    length = 150.0
    walls = (_recessed((0.0, -2.0), (length, -2.0), (0.0, -1.0), rng)
             + _recessed((0.0, 2.0), (length, 2.0), (0.0, 1.0), rng))
    walls += [Wall(0.0, -2.0, 0.0, 2.0), Wall(length, -2.0, length, 2.0)]
    # straight legs 1.25 m off the axis, a half circle at each end
    a = np.deg2rad(np.arange(-60.0, 61.0, 30.0))
    east = np.column_stack([147.0 + 1.25 * np.cos(a), 1.25 * np.sin(a)])
    west = np.column_stack([3.0 - 1.25 * np.cos(a), -1.25 * np.sin(a)])
    legs = np.arange(10.0, 141.0, 10.0)
    way = np.vstack([np.column_stack([legs, np.full_like(legs, -1.25)]), [[147.0, -1.25]], east,
                     [[147.0, 1.25]], np.column_stack([legs[::-1], np.full_like(legs, 1.25)]),
                     [[3.0, 1.25]], west, [[3.0, -1.25]]])
    return World("long_corridor", walls, way, speed=0.8)


def _office() -> World:
    # A 100 m x 48 m office floor: 4 m corridors round two blocks of rooms and between them,
    # doors (recesses) along every corridor.  One lap drives every corridor twice, once
    # each way, keeping to the right (lanes 1.2 m apart): a revisit the other way looks the
    # other way, as a robot sent back down a corridor does.  737 m a lap.
    rng = np.random.default_rng(5)
    W, H, c = 100.0, 48.0, 4.0
    walls = (_recessed((0, 0), (W, 0), (0, -1), rng) + _recessed((W, 0), (W, H), (1, 0), rng)
             + _recessed((W, H), (0, H), (0, 1), rng) + _recessed((0, H), (0, 0), (-1, 0), rng))
    for y0, y1 in ((c, H / 2 - c / 2), (H / 2 + c / 2, H - c)):
        x0, x1 = c, W - c
        walls += (_recessed((x0, y0), (x1, y0), (0, 1), rng)
                  + _recessed((x1, y0), (x1, y1), (-1, 0), rng)
                  + _recessed((x1, y1), (x0, y1), (0, -1), rng)
                  + _recessed((x0, y1), (x0, y0), (1, 0), rng))
    yb, ym, yt, xl, xr = c / 2, H / 2, H - c / 2, c / 2, W - c / 2   # corridor centre lines
    o, r = 0.6, 2.5   # lane offset; each run starts and ends r from its corner (rounded)
    runs = [((xl, yb - o), (xr, yb - o)), ((xr + o, yb), (xr + o, yt)),   # bottom E, right N
            ((xr, yt + o), (xl, yt + o)), ((xl - o, yt), (xl - o, ym)),   # top W, left S
            ((xl, ym - o), (xr, ym - o)), ((xr - o, ym), (xr - o, yb)),   # middle E, right S
            ((xr, yb + o), (xl, yb + o)), ((xl + o, yb), (xl + o, yt)),   # bottom W, left N
            ((xl, yt - o), (xr, yt - o)), ((xr - o, yt), (xr - o, ym)),   # top E, right S
            ((xr, ym + o), (xl, ym + o)), ((xl - o, ym), (xl - o, yb))]   # middle W, left S
    way = []
    for p, q in runs:
        p, q = np.asarray(p, float), np.asarray(q, float)
        u = (q - p) / np.linalg.norm(q - p)
        a, b = p + u * r, q - u * r
        n = max(int(np.linalg.norm(b - a) // 10.0), 1)
        way += [a + (b - a) * k / n for k in range(n + 1)]
    return World("office", walls, np.array(way), speed=1.0)


WORLDS = {"corridor": _corridor, "room": _room, "loop": _loop, "hall": _hall,
          "expo": _expo, "campus": _campus, "long_corridor": _long_corridor,
          "office": _office}


def get_world(name: str) -> World:
    """A fresh copy of the named world (:data:`WORLDS`)."""
    try:
        return WORLDS[name]()
    except KeyError:
        raise ValueError(f"unknown world {name!r}; choose from {', '.join(sorted(WORLDS))}") \
            from None
