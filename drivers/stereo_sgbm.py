"""Disparity from a rectified pair with OpenCV's semi-global matcher (StereoSGBM, 3-way mode).

MODE_SGBM_3WAY was the fastest good matcher measured here (DESIGN.md, about 20 ms for 640x400
with 64 disparities on 2 threads).  Parameters come from config (``SgbmParams.from_dict``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np


@dataclass
class SgbmParams:
    """StereoSGBM settings; P1/P2 default to OpenCV's recommended 8*cn*b^2 and 32*cn*b^2."""

    num_disparities: int = 64     # search range, a multiple of 16
    min_disparity: int = 0
    block_size: int = 5           # odd, 3..11
    p1: int | None = None
    p2: int | None = None
    disp12_max_diff: int = 1      # left-right consistency, pixels (-1 disables)
    pre_filter_cap: int = 63
    uniqueness_ratio: int = 10    # percent margin of the best over the second-best cost
    speckle_window_size: int = 100
    speckle_range: int = 2
    mode: str = "3way"            # "3way", "sgbm", "hh", "hh4"

    @classmethod
    def from_dict(cls, d: dict | None) -> SgbmParams:
        d = dict(d or {})
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise ValueError(f"sgbm: unknown parameter(s) {', '.join(unknown)}")
        p = cls(**d)
        if p.num_disparities <= 0 or p.num_disparities % 16:
            raise ValueError(f"sgbm: num_disparities must be a positive multiple of 16, "
                             f"got {p.num_disparities}")
        if p.block_size < 1 or p.block_size % 2 == 0:
            raise ValueError(f"sgbm: block_size must be odd and positive, got {p.block_size}")
        return p

    def to_dict(self) -> dict:
        return asdict(self)


_MODES = {"sgbm": 0, "hh": 1, "3way": 2, "hh4": 3}  # cv2.STEREO_SGBM_MODE_* values


def make_matcher(params: SgbmParams, channels: int = 1):
    """A configured ``cv2.StereoSGBM`` (reusable across frames of one size)."""
    import cv2

    b = params.block_size
    p1 = params.p1 if params.p1 is not None else 8 * channels * b * b
    p2 = params.p2 if params.p2 is not None else 32 * channels * b * b
    return cv2.StereoSGBM_create(
        minDisparity=params.min_disparity, numDisparities=params.num_disparities, blockSize=b,
        P1=p1, P2=p2, disp12MaxDiff=params.disp12_max_diff, preFilterCap=params.pre_filter_cap,
        uniquenessRatio=params.uniqueness_ratio, speckleWindowSize=params.speckle_window_size,
        speckleRange=params.speckle_range, mode=_MODES[params.mode])


def to_gray(img: np.ndarray) -> np.ndarray:
    """8-bit single-channel image (colour images are converted, 16-bit scaled down)."""
    import cv2

    img = np.asarray(img)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype != np.uint8:
        img = np.clip(img.astype(np.float64) / (256.0 if img.dtype == np.uint16 else 1.0),
                      0, 255).astype(np.uint8)
    return img


class SgbmRangeError(ValueError):
    """The disparity search range does not fit the image width."""


def check_width(params: SgbmParams, width: int) -> None:
    """Refuse a search range as wide as the image: OpenCV then computes a negative buffer size
    and fails with "Failed to allocate 18446744073... bytes" instead of saying why."""
    reach = params.num_disparities + max(params.min_disparity, 0)
    if width <= reach:
        raise SgbmRangeError(f"sgbm: num_disparities {params.num_disparities} (+ min_disparity "
                         f"{params.min_disparity}) needs images wider than {reach} px, got "
                         f"{width} px; lower num_disparities")


def compute_disparity(left: np.ndarray, right: np.ndarray, params: SgbmParams | None = None,
                      matcher=None) -> np.ndarray:
    """Disparity in pixels (float32) of the left image of a rectified pair; NaN where the
    matcher found no valid match."""
    params = params or SgbmParams()
    left, right = to_gray(left), to_gray(right)
    if left.shape != right.shape:
        raise ValueError(f"stereo pair: image sizes differ {left.shape} vs {right.shape}")
    check_width(params, left.shape[1])
    matcher = matcher or make_matcher(params)
    raw = matcher.compute(left, right)  # int16, fixed point with 4 fractional bits
    disp = raw.astype(np.float32) / 16.0
    disp[raw < (params.min_disparity * 16)] = np.nan
    return disp
