"""Camera-view occlusion: drop the LiDAR points the camera cannot see.

LiDAR and camera sit apart (KITTI: the Velodyne ~0.27 m behind and ~0.08 m above the left
camera), so the LiDAR sees background past a foreground edge where the camera sees the
foreground. Projected into the image, such a "see-through" point lands on the foreground
object with the background's depth. The test used here is the neighbourhood-minimum rule of
KITTI-style ground truth (METHODS.md section 12, rule a): a point at depth ``z`` is occluded when
the nearest point of the foreground map in a window around its pixel is nearer by more than a
relative margin,

    z > (1 + rel) * F,    F = min of the foreground depths in the window,

with a window of about ``2 * footprint_m`` metres at the point's depth, radius
``r = clip(rint(fx * footprint_m / z), min_radius_px, max_radius_px)`` pixels. A metric window
keeps a tilted surface from occluding itself: along a road seen from height h the depth grows by
a factor (1 + rel) within ``fx * h * rel / z`` rows, more than the window's ``fx * footprint_m /
z`` as long as ``footprint_m < h * rel`` (0.165 m for KITTI's 1.65 m and rel = 0.1); a wall
seen at a grazing angle from lateral distance d changes depth by ``footprint_m / d`` across the
window, so walls farther than ``footprint_m / rel`` (1 m) keep their points too.

Why this rule and not hidden point removal (Katz et al. 2007, Open3D's
``hidden_point_removal``): HPR works on the whole cloud with a convex hull from the camera
centre, needs a radius parameter tuned to the scene's depth range, and removes points of a
plane seen at a grazing angle; the window rule is a local, vectorised test that keeps planes and
fronto-parallel faces by construction (the properties section 12 asks for) and is the one
:mod:`sparsetools.ops.accumulate` already applies to the other scans of an accumulation.

Everything is vectorised (OpenCV's min filter per distinct radius, numpy gathers).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validate import (
    check_dtype,
    check_int_range,
    check_non_negative,
    check_positive,
    check_same_shape,
    check_shape,
)

__all__ = [
    "OcclusionSettings",
    "filter_occluded",
    "occluded_points",
    "occlusion_radius",
    "window_minimum",
]


@dataclass(frozen=True)
class OcclusionSettings:
    """Options of the occlusion test.

    Attributes
    ----------
    rel : float
        Relative depth margin: occluded when ``z > (1 + rel) * F`` (default 0.1).
    footprint_m : float, metres
        Half size of the window in metres at the point's depth (default 0.1; keep it below
        camera height x ``rel`` so the road does not occlude itself).
    min_radius_px, max_radius_px : int
        Bounds of the window radius in pixels (default 1 and 8). ``min_radius_px =
        max_radius_px = (w - 1) / 2`` gives a fixed w x w window.
    """

    rel: float = 0.1
    footprint_m: float = 0.1
    min_radius_px: int = 1
    max_radius_px: int = 8

    def __post_init__(self) -> None:
        check_non_negative(self.rel, "rel")
        check_positive(self.footprint_m, "footprint_m")
        lo = check_int_range(self.min_radius_px, "min_radius_px", low=0, high=64)
        check_int_range(self.max_radius_px, "max_radius_px", low=lo, high=64)


def occlusion_radius(depth: np.ndarray, *, fx: float, settings: OcclusionSettings) -> np.ndarray:
    """Window radius per point, ``clip(rint(fx * footprint_m / depth), min, max)``.

    Parameters
    ----------
    depth : (N,) float, metres, > 0
    fx : float, pixels
    settings : OcclusionSettings

    Returns
    -------
    (N,) int64, pixels
    """
    check_positive(fx, "fx")
    depth = np.asarray(depth, dtype=np.float64)
    check_shape(depth, "(N,)", "depth")
    with np.errstate(divide="ignore"):
        r = np.rint(fx * settings.footprint_m / depth)
    return np.clip(r, settings.min_radius_px, settings.max_radius_px).astype(np.int64)


def window_minimum(
    foreground: np.ndarray, radius: np.ndarray, iv: np.ndarray, iu: np.ndarray
) -> np.ndarray:
    """Minimum of the non-empty pixels of ``foreground`` in the (2r+1)^2 window of each point.

    Parameters
    ----------
    foreground : (H, W) float, metres
        Depth map; 0 = empty.
    radius : (N,) int
        Window radius of each point, pixels.
    iv, iu : (N,) int
        Row and column of each point (inside the map).

    Returns
    -------
    (N,) float64, metres
        ``+inf`` where the window holds no value.
    """
    import cv2

    check_shape(foreground, "(H, W)", "foreground")
    check_same_shape(iv, iu, "iv", "iu")
    check_same_shape(radius, iv, "radius", "iv")
    filled = np.where(foreground > 0, foreground, np.inf).astype(np.float32)
    out = np.empty(np.shape(iv)[0], np.float64)
    for r in np.unique(radius).tolist():
        sel = radius == r
        m = filled if r == 0 else cv2.erode(filled, np.ones((2 * r + 1, 2 * r + 1), np.uint8))
        out[sel] = m[iv[sel], iu[sel]]
    return out


def occluded_points(
    iu: np.ndarray,
    iv: np.ndarray,
    depth: np.ndarray,
    foreground: np.ndarray,
    *,
    fx: float,
    settings: OcclusionSettings | None = None,
) -> np.ndarray:
    """Which points lie behind the local foreground (module docstring).

    Parameters
    ----------
    iu, iv : (N,) int
        Pixel column and row of each point, inside ``foreground``.
    depth : (N,) float, metres
        Camera depth of each point.
    foreground : (H, W) float, metres
        The depth map the points are tested against (0 = empty), e.g. the z-buffer of all
        points.
    fx : float, pixels
    settings : OcclusionSettings, optional

    Returns
    -------
    (N,) bool
        True where occluded.
    """
    s = OcclusionSettings() if settings is None else settings
    check_positive(fx, "fx")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.size == 0:
        return np.zeros(0, bool)
    radius = occlusion_radius(depth, fx=fx, settings=s)
    near = window_minimum(foreground, radius, np.asarray(iv), np.asarray(iu))
    return depth > (1.0 + s.rel) * near


def filter_occluded(
    depth: np.ndarray, *, fx: float, settings: OcclusionSettings | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Remove the occluded pixels of a sparse depth map (each pixel one projected point).

    Parameters
    ----------
    depth : (H, W) float32, metres
        Sparse depth map, 0 = empty (e.g. :func:`sparsetools.ops.projection.project_points`).
    fx : float, pixels
        Focal length of the map's camera (after any resize).
    settings : OcclusionSettings, optional

    Returns
    -------
    filtered : (H, W) float32, metres
        ``depth`` with the occluded pixels set to 0.
    removed : (H, W) bool
        The pixels removed.
    """
    depth = np.asarray(depth)
    check_shape(depth, "(H, W)", "depth")
    check_dtype(depth, "depth", (np.float32, np.float64))
    iv, iu = np.nonzero(depth > 0)
    hidden = occluded_points(iu, iv, depth[iv, iu], depth, fx=fx, settings=settings)
    removed = np.zeros(depth.shape, bool)
    removed[iv[hidden], iu[hidden]] = True
    filtered = depth.copy()
    filtered[removed] = 0
    return filtered, removed
