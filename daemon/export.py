"""Map exports from the daemon's ``map`` reply: PNG, PGM + YAML (map_server), PLY, JSON.

The PLY holds the 3D plane patches (each merged plane's rectangle as a quad) and the 2D
segments extruded to ``wall_height`` as virtual walls (000 fig. 2), so the 3D map is readable
even where the camera saw little.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from cgamap.mapping.fileio import write_text_atomic

FORMATS = ("png", "pgm", "ply", "json")


def _linemap(segments: np.ndarray):
    from cgamap.mapping.linemap import LineMap

    seg = np.asarray(segments, dtype=float).reshape(-1, 4)
    return LineMap(a=seg[:, :2].copy(), b=seg[:, 2:].copy())


def export_png(map_reply: dict, path: Path, trajectory: np.ndarray | None = None,
               reference: np.ndarray | None = None, resolution: float = 0.03) -> list[Path]:
    from cgamap.mapping.render import render_png

    render_png(_linemap(map_reply["segments"]), path, trajectory=trajectory,
               reference=reference, resolution=resolution)
    return [path]


def export_pgm(map_reply: dict, path: Path, resolution: float = 0.05) -> list[Path]:
    from cgamap.mapping.render import export_occupancy

    return list(export_occupancy(_linemap(map_reply["segments"]), path.with_suffix(""),
                                 resolution=resolution))


def ply_mesh(map_reply: dict, wall_height: float = 2.5) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
    """(vertices (n, 3), quads (m, 4) vertex indices, colours (m, 3) uint8)."""
    seg = np.asarray(map_reply["segments"], dtype=float).reshape(-1, 4)
    k = len(seg)
    walls = np.zeros((k, 4, 3))
    walls[:, 0, :2], walls[:, 1, :2] = seg[:, :2], seg[:, 2:]
    walls[:, 2, :2], walls[:, 3, :2] = seg[:, 2:], seg[:, :2]
    walls[:, 2:, 2] = wall_height
    planes = [np.asarray(p["corners"], dtype=float).reshape(4, 3) for p in map_reply["planes"]
              if len(p.get("corners", [])) == 4]
    quads = np.concatenate([walls, np.asarray(planes).reshape(-1, 4, 3)])
    colours = np.concatenate([np.tile([[170, 170, 170]], (k, 1)),
                              np.tile([[40, 120, 220]], (len(planes), 1))]).astype(np.uint8)
    return quads.reshape(-1, 3), np.arange(4 * len(quads)).reshape(-1, 4), colours


def export_ply(map_reply: dict, path: Path, wall_height: float = 2.5) -> list[Path]:
    v, f, c = ply_mesh(map_reply, wall_height)
    head = ("ply\nformat ascii 1.0\ncomment cgamap: 2D segments as virtual walls (grey), "
            f"3D planes (blue)\nelement vertex {len(v)}\nproperty float x\nproperty float y\n"
            f"property float z\nelement face {len(f)}\nproperty list uchar int vertex_indices\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n")
    vert = "\n".join(f"{x:.4f} {y:.4f} {z:.4f}" for x, y, z in v)
    faces = "\n".join(f"4 {q[0]} {q[1]} {q[2]} {q[3]} {r} {g} {b}"
                      for q, (r, g, b) in zip(f, c, strict=True))
    write_text_atomic(path, head + vert + ("\n" if len(v) else "") + faces
                      + ("\n" if len(f) else ""))
    return [path]


def render_3d_png(map_reply: dict, path: Path, size: tuple[int, int] = (960, 640),
                  wall_height: float = 2.5, azimuth_deg: float = -60.0,
                  elevation_deg: float = 35.0) -> list[Path]:
    """An oblique view of the 3D map: virtual walls (grey) and camera planes (blue), painted
    far to near (orthographic projection, Lambert shading)."""
    import cv2
    from cgamap.mapping.render import write_image_atomic

    v, f, c = ply_mesh(map_reply, wall_height)
    img = np.full((size[1], size[0], 3), 255, np.uint8)
    if not len(f):
        write_image_atomic(path, img, "PNG")
        return [path]
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    fwd = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    uv = np.stack([v @ right, -(v @ up)], axis=1)
    lo, hi = uv.min(0), uv.max(0)
    scale = 0.92 * min(size[0] / max(hi[0] - lo[0], 1e-6), size[1] / max(hi[1] - lo[1], 1e-6))
    px = ((uv - (lo + hi) / 2) * scale + np.array(size) / 2).round().astype(np.int32)
    quads = v[f]                                        # (m, 4, 3)
    normal = np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0])
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    shade = 0.55 + 0.45 * np.abs(normal @ light)
    depth = (quads.mean(1) @ fwd)
    for i in np.argsort(-depth):                         # far first
        poly = px[f[i]].reshape(-1, 1, 2)
        col = tuple(int(x) for x in (c[i][::-1] * shade[i]).clip(0, 255))  # BGR
        x0, y0 = np.maximum(poly.reshape(-1, 2).min(0), 0)
        x1, y1 = poly.reshape(-1, 2).max(0) + 1
        roi = img[y0:y1, x0:x1]  # blend in the quad's box only: camera planes see-through
        layer = roi.copy()
        cv2.fillPoly(layer, [poly - [x0, y0]], col, cv2.LINE_AA)
        alpha = 0.9 if c[i][0] == c[i][1] else 0.55
        img[y0:y1, x0:x1] = cv2.addWeighted(layer, alpha, roi, 1 - alpha, 0)
        cv2.polylines(img, [poly], True, (60, 60, 60), 1, cv2.LINE_AA)
    write_image_atomic(path, img, "PNG")
    return [path]


def read_ply_counts(path: Path) -> tuple[int, int]:
    """(vertices, faces) from a PLY header (for checks)."""
    nv = nf = 0
    for line in Path(path).read_text().splitlines():
        if line.startswith("element vertex"):
            nv = int(line.split()[-1])
        elif line.startswith("element face"):
            nf = int(line.split()[-1])
        elif line == "end_header":
            break
    return nv, nf


def export(map_reply: dict, fmt: str, path: Path, **kw) -> list[Path]:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "png":
        return export_png(map_reply, path, **kw)
    if fmt == "pgm":
        return export_pgm(map_reply, path, **kw)
    if fmt == "ply":
        return export_ply(map_reply, path)
    if fmt == "json":
        write_text_atomic(path, json.dumps(map_reply, indent=1))
        return [path]
    raise ValueError(f"unknown format {fmt!r} (one of {', '.join(FORMATS)})")
