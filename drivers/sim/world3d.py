"""The simulated world in 3D: the laser twins' walls extruded, plus floor, stairs and boxes.

Every surface is a planar rectangle (``Quad``: a corner and two orthogonal edge vectors), so a
ray cast is one ray-plane intersection per (ray, quad) pair with a bounds check, vectorised in
numpy.  Each quad carries a texture seed so a renderer can paint a procedural, view-consistent
texture on it (stereo matching needs texture), and the plane (unit normal n, rho with
n.x = rho) for ground truth.

Coordinates: metres, world frame x/y as in ``world.py``, z up, floor at z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .world import WORLDS, World, get_world


@dataclass
class Scene3D:
    """Planar rectangles: corners (n, 3), edges eu and ev (n, 3, orthogonal), kinds, seeds."""

    name: str
    corner: np.ndarray
    eu: np.ndarray
    ev: np.ndarray
    kinds: list[str]
    world: World | None = None          # the 2D world (trajectory) this scene extrudes
    planes_meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.corner)

    @property
    def normals(self) -> np.ndarray:
        n = np.cross(self.eu, self.ev)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def planes(self) -> tuple[np.ndarray, np.ndarray]:
        """(normals (n, 3), rho (n,)) with n.x = rho and rho >= 0 (Hesse form)."""
        n = self.normals
        rho = np.einsum("ij,ij->i", n, self.corner)
        flip = rho < 0
        n[flip] *= -1
        return n, np.abs(rho)

    def raycast(self, origin: np.ndarray, dirs: np.ndarray, chunk: int = 32768
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """First hit along rays ``origin + t dirs`` (dirs (m, 3), not necessarily unit).

        Returns t (m,) (inf where nothing is hit), the quad index (m,) (-1 for none) and the
        hit's surface coordinates (a, b) in metres along eu and ev from the quad's corner.
        """
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        m = len(dirs)
        n = self.normals                                       # (q, 3)
        lu = np.linalg.norm(self.eu, axis=1)
        lv = np.linalg.norm(self.ev, axis=1)
        uhat, vhat = self.eu / lu[:, None], self.ev / lv[:, None]
        w = self.corner - o                                    # (q, 3)
        num = np.einsum("qi,qi->q", w, n)                      # (q,)
        # In-plane coordinates of the hit: (o + t d - corner).uhat = t (d.uhat) - w.uhat
        wu = np.einsum("qi,qi->q", w, uhat)
        wv = np.einsum("qi,qi->q", w, vhat)
        t_out = np.full(m, np.inf)
        idx_out = np.full(m, -1, dtype=np.int64)
        a_out = np.zeros(m)
        b_out = np.zeros(m)
        # float32 temporaries: half the memory traffic; t is refined in float64 below.
        n32, u32, v32 = (x.T.astype(np.float32) for x in (n, uhat, vhat))
        num32, wu32, wv32 = (x.astype(np.float32) for x in (num, wu, wv))
        lu32, lv32 = lu.astype(np.float32), lv.astype(np.float32)
        for s in range(0, m, chunk):  # chunks bound the (rays x quads) temporaries
            d = dirs[s:s + chunk]
            d32 = d.astype(np.float32)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                t = num32 / (d32 @ n32)                        # (c, q); inf/nan if parallel
                a = t * (d32 @ u32)
                a -= wu32
                ok = (t > 1e-6) & (a >= 0) & (a <= lu32)
                a = t * (d32 @ v32)
                a -= wv32
                ok &= (a >= 0) & (a <= lv32)
            t[~ok] = np.inf
            k = np.argmin(t, axis=1)
            hit = np.isfinite(t[np.arange(len(d)), k])
            kk = k[hit]
            dh = d[hit]
            # Exact float64 hit on the chosen quad only.
            th = num[kk] / np.einsum("ij,ij->i", dh, n[kk])
            sl = np.arange(s, s + len(d))[hit]
            t_out[sl] = th
            idx_out[sl] = kk
            a_out[sl] = th * np.einsum("ij,ij->i", dh, uhat[kk]) - wu[kk]
            b_out[sl] = th * np.einsum("ij,ij->i", dh, vhat[kk]) - wv[kk]
        return t_out, idx_out, a_out, b_out


class SceneBuilder:
    """Collects quads; ``box``, ``stairs``, ``floor`` and ``extrude`` add common shapes."""

    def __init__(self) -> None:
        self.corner: list = []
        self.eu: list = []
        self.ev: list = []
        self.kinds: list[str] = []

    def quad(self, corner, eu, ev, kind: str) -> SceneBuilder:
        self.corner.append(np.asarray(corner, float))
        self.eu.append(np.asarray(eu, float))
        self.ev.append(np.asarray(ev, float))
        self.kinds.append(kind)
        return self

    def extrude(self, world: World) -> SceneBuilder:
        """Each 2D wall as a vertical rectangle from z0 to z0 + height."""
        for w in world.walls:  # a few dozen walls, not points
            self.quad((w.x0, w.y0, w.z0), (w.x1 - w.x0, w.y1 - w.y0, 0.0),
                      (0.0, 0.0, w.height), w.kind)
        tops = _rect_tops(world)
        for (x0, y0, x1, y1, z) in tops:
            self.quad((x0, y0, z), (x1 - x0, 0, 0), (0, y1 - y0, 0), "top")
        return self

    def floor(self, x0: float, y0: float, x1: float, y1: float, z: float = 0.0,
              kind: str = "floor") -> SceneBuilder:
        return self.quad((x0, y0, z), (x1 - x0, 0, 0), (0, y1 - y0, 0), kind)

    def box(self, x0: float, y0: float, z0: float, x1: float, y1: float, z1: float,
            kind: str = "box") -> SceneBuilder:
        """An axis-aligned box: four sides and the top."""
        dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
        self.quad((x0, y0, z0), (dx, 0, 0), (0, 0, dz), kind)
        self.quad((x0, y1, z0), (dx, 0, 0), (0, 0, dz), kind)
        self.quad((x0, y0, z0), (0, dy, 0), (0, 0, dz), kind)
        self.quad((x1, y0, z0), (0, dy, 0), (0, 0, dz), kind)
        return self.quad((x0, y0, z1), (dx, 0, 0), (0, dy, 0), kind)

    def stairs(self, x0: float, y0: float, y1: float, steps: int, rise: float, run: float,
               z0: float = 0.0) -> SceneBuilder:
        """A straight stairway climbing in +x from x0: treads (horizontal) and risers."""
        width = y1 - y0
        for i in range(steps):
            x, z = x0 + i * run, z0 + i * rise
            self.quad((x, y0, z), (0, width, 0), (0, 0, rise), "riser")
            self.quad((x, y0, z + rise), (run, 0, 0), (0, width, 0), "tread")
        return self

    def build(self, name: str, world: World | None = None) -> Scene3D:
        return Scene3D(name=name, corner=np.array(self.corner), eu=np.array(self.eu),
                       ev=np.array(self.ev), kinds=list(self.kinds), world=world)


def _rect_tops(world: World) -> list[tuple[float, float, float, float, float]]:
    """Tops of closed axis-aligned rectangles of non-wall kind lower than 2 m (tables,
    cabinets, boxes): four consecutive walls of one kind that close on themselves."""
    out = []
    ws = world.walls
    for i in range(len(ws) - 3):
        quad = ws[i:i + 4]
        if quad[0].kind == "wall" or any(w.kind != quad[0].kind for w in quad):
            continue
        if (quad[3].x1, quad[3].y1) != (quad[0].x0, quad[0].y0) or quad[0].height >= 2.0:
            continue
        xs = [w.x0 for w in quad]
        ys = [w.y0 for w in quad]
        out.append((min(xs), min(ys), max(xs), max(ys), quad[0].z0 + quad[0].height))
    return out


def _extruded(world: World, margin: float = 0.5) -> SceneBuilder:
    x0, y0, x1, y1 = world.bounds()
    return SceneBuilder().extrude(world).floor(x0 - margin, y0 - margin, x1 + margin,
                                               y1 + margin)


def scene_from_world(world: World, margin: float = 0.5) -> Scene3D:
    """The 2D world extruded, with a floor under its bounds."""
    return _extruded(world, margin).build(world.name, world)


def _stairs_scene() -> Scene3D:
    # The corridor, whose far end opens onto a stairway of 6 steps (rise 0.17, run 0.30).
    world = get_world("corridor")
    b = SceneBuilder()
    walls = [w for w in world.walls if not (w.x0 == 20 and w.x1 == 20)]
    world2 = World("stairs", walls, world.waypoints, world.speed)
    b.extrude(world2).floor(-0.5, -2.3, 20.0, 2.3)
    b.stairs(20.0, -1.0, 1.0, steps=6, rise=0.17, run=0.30)
    b.quad((21.8, -1.0, 0.0), (0, 2.0, 0), (0, 0, 3.5), "wall")   # end wall above the top
    b.quad((20.0, -1.0, 0.0), (1.8, 0, 0), (0, 0, 2.5), "wall")   # stair side walls
    b.quad((20.0, 1.0, 0.0), (1.8, 0, 0), (0, 0, 2.5), "wall")
    return b.build("stairs", world2)


def _corridor_boxes() -> Scene3D:
    world = get_world("corridor")
    b = _extruded(world)
    b.box(4.0, 0.4, 0.0, 4.6, 1.0, 0.5).box(15.0, -1.0, 0.0, 15.8, -0.5, 0.8)
    return b.build("corridor-boxes", world)


SCENES = {"stairs": _stairs_scene, "corridor-boxes": _corridor_boxes}


def get_scene(name: str) -> Scene3D:
    """A 3D scene by name: any 2D world of ``world.py`` extruded with a floor, or one of
    the 3D-only scenes ("stairs", "corridor-boxes")."""
    if name in SCENES:
        return SCENES[name]()
    if name not in WORLDS:
        raise ValueError(f"unknown world {name!r}; choose from "
                         f"{', '.join(sorted(WORLDS) + sorted(SCENES))}")
    return scene_from_world(get_world(name))
