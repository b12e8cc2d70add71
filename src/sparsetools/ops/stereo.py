"""KITTI's stereo consistency check of LiDAR ground truth: drop points that disagree with stereo.

KITTI's annotated depth maps (Uhrig et al., *Sparsity Invariant CNNs*, 3DV 2017) remove the
accumulated LiDAR points that disagree with a semi-global matching disparity map of the
rectified stereo pair (METHODS.md section 12). Here the disparity comes from OpenCV's
``StereoSGBM`` (Hirschmueller's SGM with block costs) of the rectified pair, left = the
ground truth's camera (KITTI ``image_02``), right = the other (``image_03``); a point of depth
``z`` has the disparity ``d_lidar = fx * baseline / z``.

**The margin.** A point is *inconsistent* when its disparity differs from the stereo one by
more than ``abs_px`` pixels AND more than ``rel`` of its own disparity: KITTI's own outlier
rule for disparities (the stereo 2015 benchmark's D1 error: more than 3 px and more than
5 %), the defaults. In depth this is a band that widens with distance as stereo's own error
does (``dz ~ z^2 / (fx B) dd``): at fx = 721 px, B = 0.533 m the 5 % term rules nearer than
6.4 m (d > 60 px; +-0.25 m at 5 m), the 3 px term farther (about +-1.8 m at 15 m, -5.7 / +9.2 m
at 30 m). A see-through point (background depth on a foreground object) or a moving
object's trace differs by far more; SGBM's own mistakes on weak texture are usually within
it. Where SGBM has no valid disparity (occluded in the right image, weak texture, the left
``num_disparities`` columns, points nearer than ``fx B / num_disparities``, speckles removed)
the point is kept: stereo has no opinion there.

Everything is vectorised (OpenCV's SGBM, numpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validate import (
    check_choice,
    check_dtype,
    check_int_range,
    check_multiple,
    check_non_negative,
    check_odd,
    check_positive,
    check_same_shape,
    check_shape,
)

__all__ = [
    "SGBM_MODES",
    "SgbmSettings",
    "StereoCheckSettings",
    "sgbm_disparity",
    "stereo_check",
    "stereo_outliers",
]

SGBM_MODES = ("sgbm", "hh", "3way")


@dataclass(frozen=True)
class SgbmSettings:
    """OpenCV ``StereoSGBM`` options (the usual KITTI settings; OpenCV's names in brackets).

    Attributes
    ----------
    num_disparities : int
        Disparity search range in pixels, a multiple of 16 [numDisparities] (default 128:
        nearest depth ``fx B / 128`` = 3.0 m on KITTI).
    block_size : int
        Odd matching block side, pixels [blockSize] (default 5); the smoothness penalties are
        ``P1 = 8 * 3 * block_size**2`` and ``P2 = 32 * 3 * block_size**2`` (OpenCV's
        recommendation).
    uniqueness_ratio : int
        Percent by which the best cost must beat the second best [uniquenessRatio] (10).
    speckle_window_size, speckle_range : int
        Connected disparity blobs smaller than this many pixels varying by more than this many
        pixels are invalidated [speckleWindowSize, speckleRange] (100, 2).
    disp12_max_diff : int
        Largest left-right check difference, pixels [disp12MaxDiff] (1).
    mode : {"sgbm", "hh", "3way"}
        5-direction SGBM, full 8-direction (MODE_HH) or OpenCV's faster 3-way variant.
    """

    num_disparities: int = 128
    block_size: int = 5
    uniqueness_ratio: int = 10
    speckle_window_size: int = 100
    speckle_range: int = 2
    disp12_max_diff: int = 1
    mode: str = "sgbm"

    def __post_init__(self) -> None:
        check_multiple(self.num_disparities, "num_disparities", of=16, low=16, high=1024)
        check_odd(self.block_size, "block_size", low=1, high=31)
        check_int_range(self.uniqueness_ratio, "uniqueness_ratio", low=0, high=100)
        check_int_range(self.speckle_window_size, "speckle_window_size", low=0)
        check_int_range(self.speckle_range, "speckle_range", low=0)
        check_int_range(self.disp12_max_diff, "disp12_max_diff", low=-1)
        check_choice(self.mode, "mode", SGBM_MODES)


@dataclass(frozen=True)
class StereoCheckSettings:
    """The consistency margin (module docstring) and the matcher.

    Attributes
    ----------
    abs_px : float, pixels
        Disparity difference a point may have whatever its depth (default 3, KITTI's D1).
    rel : float
        Relative disparity difference a point may have (default 0.05, KITTI's D1).
    sgbm : SgbmSettings
    """

    abs_px: float = 3.0
    rel: float = 0.05
    sgbm: SgbmSettings = SgbmSettings()

    def __post_init__(self) -> None:
        check_non_negative(self.abs_px, "abs_px")
        check_non_negative(self.rel, "rel")


def _gray(image: np.ndarray, name: str) -> np.ndarray:
    import cv2

    image = np.asarray(image)
    check_dtype(image, name, (np.uint8,))
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(image, code)
    check_shape(image, "(H, W)", name, nonempty=True)
    return image


def sgbm_disparity(
    left: np.ndarray, right: np.ndarray, *, settings: SgbmSettings | None = None
) -> np.ndarray:
    """Disparity of the left image of a rectified pair by OpenCV's semi-global matching.

    Parameters
    ----------
    left, right : (H, W) or (H, W, 3) uint8
        The rectified pair (colour images are taken as BGR and matched in grey).
    settings : SgbmSettings, optional

    Returns
    -------
    (H, W) float32, pixels
        ``x_left - x_right`` of each left pixel's match; NaN where SGBM found none.
    """
    import cv2

    s = SgbmSettings() if settings is None else settings
    gl, gr = _gray(left, "left"), _gray(right, "right")
    check_same_shape(gl, gr, "left", "right")
    modes = {"sgbm": cv2.STEREO_SGBM_MODE_SGBM, "hh": cv2.STEREO_SGBM_MODE_HH,
             "3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY}  # fmt: skip
    matcher = cv2.StereoSGBM_create(
        minDisparity=0,
        numDisparities=s.num_disparities,
        blockSize=s.block_size,
        P1=8 * 3 * s.block_size**2,
        P2=32 * 3 * s.block_size**2,
        disp12MaxDiff=s.disp12_max_diff,
        uniquenessRatio=s.uniqueness_ratio,
        speckleWindowSize=s.speckle_window_size,
        speckleRange=s.speckle_range,
        mode=modes[s.mode],
    )
    fixed = matcher.compute(gl, gr)  # int16, disparity * 16; invalid: (minDisparity - 1) * 16
    disparity = fixed.astype(np.float32) / np.float32(16.0)
    disparity[fixed < 0] = np.nan
    return disparity


def stereo_outliers(
    depth: np.ndarray,
    disparity: np.ndarray,
    *,
    fx: float,
    baseline: float,
    settings: StereoCheckSettings | None = None,
) -> np.ndarray:
    """The pixels of a sparse depth map whose depth disagrees with the stereo disparity.

    Parameters
    ----------
    depth : (H, W) float, metres
        Sparse depth map of the left camera, 0 = empty.
    disparity : (H, W) float, pixels
        The left image's disparity (:func:`sgbm_disparity`), NaN = none.
    fx : float, pixels
        Focal length of the rectified pair.
    baseline : float, metres
        Distance between the two cameras' centres (KITTI 2/3: 0.532 m).
    settings : StereoCheckSettings, optional

    Returns
    -------
    (H, W) bool
        True where the map has a value, stereo has a disparity and they differ by more than
        ``abs_px`` and more than ``rel`` of the point's disparity.
    """
    s = StereoCheckSettings() if settings is None else settings
    check_positive(fx, "fx")
    check_positive(baseline, "baseline")
    depth = np.asarray(depth)
    check_shape(depth, "(H, W)", "depth")
    check_same_shape(depth, disparity, "depth", "disparity")
    valid = (depth > 0) & np.isfinite(disparity)
    out = np.zeros(depth.shape, bool)
    z = depth[valid].astype(np.float64)
    d_lidar = fx * baseline / z
    err = np.abs(d_lidar - disparity[valid].astype(np.float64))
    out[valid] = (err > s.abs_px) & (err > s.rel * d_lidar)
    return out


def stereo_check(
    depth: np.ndarray,
    left: np.ndarray,
    right: np.ndarray,
    *,
    fx: float,
    baseline: float,
    settings: StereoCheckSettings | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Remove the points of a sparse depth map that disagree with the stereo pair.

    Parameters
    ----------
    depth : (H, W) float32, metres
        Sparse depth map of the left camera, 0 = empty.
    left, right : (H, W) or (H, W, 3) uint8
        The rectified pair, left = the map's camera.
    fx : float, pixels
    baseline : float, metres
    settings : StereoCheckSettings, optional

    Returns
    -------
    filtered : (H, W) float32, metres
        ``depth`` with the inconsistent pixels set to 0.
    removed : (H, W) bool
    disparity : (H, W) float32, pixels
        SGBM's disparity (NaN = none).
    """
    s = StereoCheckSettings() if settings is None else settings
    depth = np.asarray(depth)
    check_shape(depth, "(H, W)", "depth")
    check_dtype(depth, "depth", (np.float32, np.float64))
    disparity = sgbm_disparity(left, right, settings=s.sgbm)
    check_same_shape(disparity, depth, "the stereo pair", "the depth map")
    removed = stereo_outliers(depth, disparity, fx=fx, baseline=baseline, settings=s)
    filtered = depth.copy()
    filtered[removed] = 0
    return filtered, removed, disparity
