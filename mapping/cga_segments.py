"""Segments as CGA entities (seed §IV-A): point pairs, lines (eq. 28), spheres (eq. 12), Hough.

A segment with end points a, b in the laser frame is the OPNS point pair PP = up(a) ^ up(b).
It reaches the global frame through the laser chain M_GL = M_GB M_BL (DESIGN.md): every
entity X goes to M X ~M.  Its line is PP ^ einf (eq. 28), its Hough parameters (theta, rho)
follow from the line, and its sphere is the one whose equator is the pair (eq. 12).

The mapper's hot path moves only the segments' points and moments, by the planar pose of
the chain motor (:func:`segments_to_global`): the same transform as the sandwich on the
point pair, which the tests pin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from cgamap.cga import (
    Multivector,
    apply,
    einf,
    hough2d_from_points,
    laser_chain,
    line_from_point_pair,
    motor_from_pose2d,
    motor_to_pose2d,
    point_pair,
    sphere_center_radius,
    sphere_from_point_pair,
)

from .segments import Segments


@dataclass
class CGASegments:
    """Batched CGA forms of k segments in one frame."""

    pairs: Multivector    # (k,) OPNS point pairs a ^ b
    lines: Multivector    # (k,) OPNS lines a ^ b ^ einf (eq. 28)
    spheres: Multivector  # (k,) IPNS spheres up(c) - r^2/2 einf (eq. 12)
    theta: np.ndarray     # Hough angle in [0, 2 pi)
    rho: np.ndarray       # Hough distance >= 0


def _xyz(p: np.ndarray) -> np.ndarray:
    return np.column_stack([p, np.zeros(len(p))])


def laser_motor(pose, mount=None) -> Multivector:
    """M_GL = M_GB M_BL for a planar robot pose (x, y, theta) and a planar mount (or None);
    planar motors are the core's closed form (microseconds per scan)."""
    M_GB = motor_from_pose2d(*pose)
    return M_GB if mount is None else laser_chain(M_GB, motor_from_pose2d(*mount))


def cga_segments(seg: Segments, M: Multivector | None = None) -> CGASegments:
    """Point pairs of ``seg`` moved by motor M (sandwich M PP ~M), with lines, spheres, Hough."""
    PP = point_pair(_xyz(seg.a), _xyz(seg.b))
    if M is not None:
        PP = apply(M, PP)
    L = line_from_point_pair(PP)
    S = sphere_from_point_pair(PP)
    a, b = pair_endpoints(PP)
    theta, rho = hough2d_from_points(a, b)
    return CGASegments(PP, L, S, theta, rho)


def pair_endpoints(PP: Multivector) -> tuple[np.ndarray, np.ndarray]:
    """The two points of OPNS point pairs, (k, 2) each, in the pair's order.

    For PP = A ^ B: the points are (PP -/+ sqrt(PP^2)) einf.PP up to weight; the order is
    recovered by which one comes out first in A ^ B's orientation.
    """
    sq = (PP * PP).scalar_part()
    root = np.sqrt(np.maximum(sq, 0.0))
    P = (einf | PP)  # a vector; (PP + sqrt) P and (PP - sqrt) P give the two points
    X1 = ((PP - Multivector.scalar(root)) * P).grade(1)
    X2 = ((PP + Multivector.scalar(root)) * P).grade(1)
    w1 = X1.v[..., 5] - X1.v[..., 4]
    w2 = X2.v[..., 5] - X2.v[..., 4]
    x1 = X1.v[..., 1:3] / w1[..., None]
    x2 = X2.v[..., 1:3] / w2[..., None]
    return x1, x2


def sphere_centre_radius_2d(S: Multivector) -> tuple[np.ndarray, np.ndarray]:
    c, r = sphere_center_radius(S)
    return c[..., :2], r


def segments_to_global(seg: Segments, M: Multivector) -> Segments:
    """``seg`` moved into the global frame by the laser chain motor M = M_GB M_BL."""
    return seg.transformed(*(float(v) for v in motor_to_pose2d(M)))
