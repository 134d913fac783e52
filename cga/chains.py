"""The sensor motor chains of DESIGN.md (seed 000 eqs. 13-22, with their typos fixed)."""

from __future__ import annotations

from .algebra import Multivector
from .versors import apply, translator


def laser_chain(M_GB: Multivector, M_BL: Multivector) -> Multivector:
    """Motor from the laser frame to the global frame: M_GL = M_GB M_BL (eqs. 13-16).

    M_GB = T_pos R_pos is the robot pose, M_BL the laser mount from calibration.
    """
    return M_GB * M_BL


def camera_chain(
    T_pos: Multivector,
    R_pos: Multivector,
    R_pan: Multivector,
    R_tilt: Multivector,
    t_axis,
    t_eye,
    R_eye: Multivector | None = None,
) -> Multivector:
    """Motor from the left camera frame to the global frame (eqs. 17-22, corrected).

    R_pt = R_pos R_pan R_tilt;  T_ap = R_pos T_axis ~R_pos;  T_opt = R_pt T_eye ~R_pt;
    M = T_opt T_ap T_pos R_pt.  ``t_axis`` is the pan-tilt axis point in the base frame,
    ``t_eye`` the camera centre in the tilted head frame; ``R_eye`` an optional fixed rotation
    from the head frame to the camera's optical frame (x right, y down, z forward), applied last.
    """
    R_pt = R_pos * R_pan * R_tilt
    T_ap = apply(R_pos, translator(t_axis))
    T_opt = apply(R_pt, translator(t_eye))
    M = T_opt * T_ap * T_pos * R_pt
    return M if R_eye is None else M * R_eye
