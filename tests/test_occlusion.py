"""ops.occlusion: the camera-view occlusion test (see-through LiDAR points)."""

from __future__ import annotations

import numpy as np
import pytest

from sparsetools.calibration import Calibration
from sparsetools.errors import ParameterError
from sparsetools.ops.accumulate import AccumulateSettings, accumulate_scans
from sparsetools.ops.occlusion import (
    OcclusionSettings,
    filter_occluded,
    occluded_points,
    occlusion_radius,
)
from sparsetools.ops.projection import project_points

FX = 100.0
CX, CY = 80.2, 60.3  # off the half-pixel grid: no constructed point on a pixel border
CALIB = Calibration(
    K=[[FX, 0, CX], [0, FX, CY], [0, 0, 1]], T_cam_from_sensor=np.eye(4), width=160, height=120
)
# KITTI's left camera (2011_09_26): the 1-px minimum window stops protecting a road seen from
# h = 1.65 m beyond fx * h * rel = 119 m, a wall at lateral distance d beyond fx * d * rel.
KITTI = Calibration(
    K=[[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1]],
    T_cam_from_sensor=np.eye(4), width=1242, height=375,
)  # fmt: skip


def reference_filter(depth: np.ndarray, fx: float, s: OcclusionSettings) -> np.ndarray:
    """Brute force, pixel by pixel: the removed mask of the neighbourhood-minimum rule."""
    h, w = depth.shape
    removed = np.zeros(depth.shape, bool)
    for v, u in zip(*np.nonzero(depth > 0), strict=True):
        z = float(depth[v, u])
        r = int(min(max(round(fx * s.footprint_m / z), s.min_radius_px), s.max_radius_px))
        win = depth[max(v - r, 0) : min(v + r + 1, h), max(u - r, 0) : min(u + r + 1, w)]
        removed[v, u] = z > (1 + s.rel) * float(win[win > 0].min())
    return removed


def grid(x0, x1, y0, y1, z, step):
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    "settings",
    [OcclusionSettings(), OcclusionSettings(rel=0.3, footprint_m=0.5, min_radius_px=0),
     OcclusionSettings(min_radius_px=2, max_radius_px=2)],
)  # fmt: skip
def test_equals_a_brute_force_reference(seed, settings):
    rng = np.random.default_rng(seed)
    depth = np.zeros((40, 57), np.float32)
    n = 300
    depth[rng.integers(0, 40, n), rng.integers(0, 57, n)] = rng.uniform(0.5, 60, n)
    filtered, removed = filter_occluded(depth, fx=FX, settings=settings)
    np.testing.assert_array_equal(removed, reference_filter(depth, FX, settings))
    assert np.all(filtered[removed] == 0)
    np.testing.assert_array_equal(filtered[~removed], depth[~removed])


def test_see_through_point_behind_a_box_is_removed_and_the_box_kept():
    # Box face at 5 m; the LiDAR, 0.3 m off the camera, saw the wall at 20 m past its edge.
    box = grid(-0.5, 0.5, -0.5, 0.5, 5.0, 0.02)
    wall = grid(-8, 8, -6, 6, 20.0, 0.2)
    cam_hidden = (np.abs(wall[:, 0] * 5 / 20) <= 0.5) & (np.abs(wall[:, 1] * 5 / 20) <= 0.5)
    see_through = wall[cam_hidden][::7]  # a few wall points the camera cannot see
    visible_wall = wall[~cam_hidden]
    depth = project_points(np.vstack([visible_wall, box]), CALIB)
    # The see-through points land where the box is nearer: put them into empty box pixels.
    assert see_through.shape[0] > 5
    u = np.rint(FX * see_through[:, 0] / 20 + CX).astype(int)
    v = np.rint(FX * see_through[:, 1] / 20 + CY).astype(int)
    depth[v, u] = 20.0
    _, removed = filter_occluded(depth, fx=FX)
    assert removed[v, u].all()
    box_px = project_points(box, CALIB) > 0
    box_px[v, u] = False
    assert not removed[box_px].any()
    wall_px = project_points(visible_wall, CALIB) > 0
    # Wall pixels whose window reaches the box's edge are behind it too (they border it); the
    # others are all kept.
    assert removed[wall_px].mean() < 0.02


def test_a_road_seen_from_camera_height_keeps_every_point():
    # Flat ground 1.65 m below the camera (y down), 2..80 m ahead, LiDAR-like rings.
    z = np.geomspace(2.0, 80.0, 60)
    x = np.linspace(-10, 10, 200)
    xs, zs = np.meshgrid(x, z)
    road = np.column_stack([xs.ravel(), np.full(xs.size, 1.65), zs.ravel()])
    depth = project_points(road, KITTI)
    assert (depth > 0).sum() > 5000
    _, removed = filter_occluded(depth, fx=KITTI.fx)
    assert removed.sum() == 0
    # With a focal length of 100 px the limit is 16.5 m: the far road is (wrongly) dropped,
    # and only there.
    depth = project_points(road, CALIB)
    _, removed = filter_occluded(depth, fx=FX)
    iv, iu = np.nonzero(removed)
    assert removed.sum() > 0 and depth[iv, iu].min() > 16.5 / 1.1 - 1e-6


def test_fronto_parallel_face_and_wall_keep_every_point():
    depth = project_points(grid(-3, 3, -2, 2, 7.0, 0.05), CALIB)
    _, removed = filter_occluded(depth, fx=FX)
    assert (depth > 0).sum() > 1000 and removed.sum() == 0
    # A wall 3 m to the side, seen at a grazing angle.
    ys, zs = np.meshgrid(np.linspace(-1, 1, 40), np.linspace(4, 40, 300))
    wall = np.column_stack([np.full(ys.size, 3.0), ys.ravel(), zs.ravel()])
    depth = project_points(wall, KITTI)
    _, removed = filter_occluded(depth, fx=KITTI.fx)
    assert (depth > 0).sum() > 3000 and removed.sum() == 0


def test_edge_cases():
    empty = np.zeros((8, 9), np.float32)
    f, r = filter_occluded(empty, fx=FX)
    assert not f.any() and not r.any()
    one = empty.copy()
    one[0, 8] = 3.0  # a single point at the image corner
    f, r = filter_occluded(one, fx=FX)
    np.testing.assert_array_equal(f, one)
    two = empty.copy()
    two[0, 0], two[0, 1] = 2.0, 50.0  # border pixels, far one behind
    f, r = filter_occluded(two, fx=FX)
    assert r[0, 1] and not r[0, 0]
    assert occluded_points(np.zeros(0, int), np.zeros(0, int), np.zeros(0), empty, fx=FX).shape == (
        0,
    )
    # Radius: rint(fx * footprint / z) clipped.
    np.testing.assert_array_equal(
        occlusion_radius(np.array([0.5, 1.0, 10.0, 1000.0]), fx=FX, settings=OcclusionSettings()),
        [8, 8, 1, 1],
    )


def test_bad_input_is_refused():
    with pytest.raises(ParameterError):
        filter_occluded(np.zeros((2, 3, 4), np.float32), fx=FX)
    with pytest.raises(ParameterError):
        filter_occluded(np.zeros((2, 3), np.int32), fx=FX)
    with pytest.raises(ParameterError):
        filter_occluded(np.zeros((2, 3), np.float32), fx=0.0)
    with pytest.raises(ParameterError):
        OcclusionSettings(rel=-0.1)
    with pytest.raises(ParameterError):
        OcclusionSettings(min_radius_px=3, max_radius_px=2)


def test_accumulate_occlude_own_drops_frame_t_see_through_points():
    box = grid(-0.5, 0.5, -0.5, 0.5, 5.0, 0.02)
    wall = grid(-8, 8, -6, 6, 20.0, 0.2)
    cam_hidden = (np.abs(wall[:, 0] * 5 / 20) <= 0.5) & (np.abs(wall[:, 1] * 5 / 20) <= 0.5)
    inner = cam_hidden & (np.abs(wall[:, 0]) < 1.6) & (np.abs(wall[:, 1]) < 1.6)
    see_through = wall[inner]
    scan = np.vstack([box[::3], wall[~cam_hidden], see_through])
    poses = np.eye(4)[None]
    plain = accumulate_scans([scan], poses, CALIB, reference=0)
    own = accumulate_scans([scan], poses, CALIB, reference=0,
                           settings=AccumulateSettings(occlude_own=True))  # fmt: skip
    assert plain.counts.occluded == 0
    # Every see-through point that reached the map is dropped; no box point is.
    assert own.counts.occluded >= 1
    assert not np.any(np.isclose(own.depth, 20.0) & (project_points(box, CALIB) > 0)
                      & (plain.depth < 20.0))  # fmt: skip
    box_kept = np.isclose(own.depth, 5.0).sum()
    assert box_kept == np.isclose(plain.depth, 5.0).sum()
    with pytest.raises(ParameterError):
        AccumulateSettings(occlude_own="yes")
