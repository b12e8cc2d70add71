"""Accumulated depth (sparsetools.ops.accumulate): synthetic sequences with exact poses and
constructed occlusion / moving-object scenes whose hidden points are computed here by ray
geometry."""

from __future__ import annotations

import numpy as np
import pytest

from sparsetools.calibration import Calibration
from sparsetools.errors import ParameterError
from sparsetools.ops.accumulate import AccumulateSettings, accumulate_scans
from sparsetools.ops.projection import project_points, project_points_with_index

NO_FILTERS = AccumulateSettings(occlusion_rel=None, consistency_rel=None)


def pose(x=0.0, y=0.0, z=0.0, yaw_deg=0.0) -> np.ndarray:
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = (x, y, z)
    return T


def transform(T, pts):
    return pts[:, :3] @ T[:3, :3].T + T[:3, 3]


# -- static synthetic street with exact poses ----------------------------------------------------


@pytest.fixture(scope="module")
def street():
    from sparsetools.synth import Rig, ego_origin, simulate_frame

    rig = Rig.kitti(621, 188)
    frames = list(range(8, 13))
    sims = [simulate_frame(0, f, rig=rig) for f in frames]
    poses = np.array([pose(*ego_origin(f, rig)) for f in frames])
    return rig, frames, sims, poses


def outlier_tolerance(gt: np.ndarray, noise_m: float) -> np.ndarray:
    """Per-pixel tolerance: 3 sigma of range noise plus what half a pixel of the surface's
    slope allows (a point lands up to 0.5 px from the pixel centre where the truth is taken).
    The slope is the smaller one-sided difference, so a depth edge does not widen it."""
    g = gt.astype(np.float64)
    du = np.full(g.shape, np.inf)
    dv = np.full(g.shape, np.inf)
    a = np.abs(np.diff(g, axis=1))
    du[:, 1:] = np.minimum(du[:, 1:], a)
    du[:, :-1] = np.minimum(du[:, :-1], a)
    a = np.abs(np.diff(g, axis=0))
    dv[1:] = np.minimum(dv[1:], a)
    dv[:-1] = np.minimum(dv[:-1], a)
    return 3 * noise_m + 0.5 * (du + dv)


def agreement(depth, gt, tol):
    both = (depth > 0) & (gt > 0)
    err = np.abs(depth[both].astype(np.float64) - gt[both])
    return float(np.mean(err > tol[both])), float(np.median(err)), int(both.sum())


def test_static_sequence_with_exact_poses_agrees_with_the_dense_truth(street):
    rig, _frames, sims, poses = street
    t = 2
    gt = sims[t].depth
    tol = outlier_tolerance(gt, rig.lidar_range_noise)
    scans = [s.points for s in sims]
    single = project_points(scans[t], rig.calibration)
    raw = accumulate_scans(scans, poses, rig.calibration, reference=t, settings=NO_FILTERS)
    res = accumulate_scans(scans, poses, rig.calibration, reference=t)
    out_single, med_single, n_single = agreement(single, gt, tol)
    out_raw, _, _ = agreement(raw.depth, gt, tol)
    out_acc, med_acc, n_acc = agreement(res.depth, gt, tol)
    print(
        f"\n621x188, frames t-2..t+2: single scan {n_single} px, {out_single:.2%} outliers, "
        f"median |err| {med_single * 100:.2f} cm; accumulated {n_acc} px, {out_acc:.2%} "
        f"outliers (unfiltered {out_raw:.2%}), median {med_acc * 100:.2f} cm; {res.counts}"
    )
    # Measured: 16.1 % -> 44.6 % of the pixels; outliers 2.7 % (single: LiDAR-camera
    # parallax, mixed pixels) -> 2.6 % unfiltered -> 1.7 % filtered; median 2.0-2.2 cm.
    assert n_acc > 2.5 * n_single
    assert out_acc < 0.025 and out_acc < out_single and out_acc < out_raw
    assert med_acc < 2 * rig.lidar_range_noise
    assert res.counts.occluded > 0
    # Frame t's own points all stay (nearest wins: no pixel of the single-scan map got
    # deeper), and every scan contributes.
    own = single > 0
    assert np.all(res.depth[own] <= single[own])
    assert set(np.unique(res.source).tolist()) == {-1, 0, 1, 2, 3, 4}


def test_counts_add_up_and_match_the_projection(street):
    rig, _frames, sims, poses = street
    scans = [s.points.copy() for s in sims]
    scans[0][:5, :3] = np.nan
    res = accumulate_scans(scans, poses, rig.calibration, reference=2)
    c = res.counts
    assert c.points == sum(s.shape[0] for s in scans)
    parts = (
        c.non_finite
        + c.behind_camera
        + c.beyond_max_depth
        + c.outside_image
        + c.masked
        + c.occluded
        + c.inconsistent
        + c.held_out
        + c.kept
    )
    assert parts == c.points
    assert c.non_finite == 5 == res.counts_per_scan[0].non_finite
    # The own scan is never filtered: its "kept" is the number project_points lands.
    own = res.counts_per_scan[2]
    _, n_in = project_points(scans[2], rig.calibration, return_count=True)
    assert own.kept == n_in and own.occluded == own.inconsistent == own.masked == 0
    # behind the camera = depth <= 0.1 m, computed independently
    for k, s in enumerate(scans):
        T = np.linalg.inv(poses[2]) @ poses[k]
        cam = transform(rig.calibration.T_cam_from_sensor @ T, s)
        finite = np.isfinite(cam).all(axis=1)
        assert res.counts_per_scan[k].behind_camera == int(np.sum(cam[finite, 2] <= 0.1))


def test_reference_alone_is_the_projection(street):
    rig, _frames, sims, poses = street
    pts = sims[1].points
    res = accumulate_scans([pts], poses[1:2], rig.calibration, reference=0)
    np.testing.assert_array_equal(res.depth, project_points(pts, rig.calibration))
    np.testing.assert_array_equal(res.source, np.where(res.depth > 0, 0, -1))


def test_without_filters_it_is_one_zbuffer_over_the_moved_points(street):
    rig, _frames, sims, poses = street
    scans = [s.points for s in sims]
    res = accumulate_scans(scans, poses, rig.calibration, reference=1, settings=NO_FILTERS)
    moved = np.concatenate(
        [transform(np.linalg.inv(poses[1]) @ poses[k], s) for k, s in enumerate(scans)]
    )
    owner = np.concatenate([np.full(s.shape[0], k) for k, s in enumerate(scans)])
    depth, index = project_points_with_index(moved, rig.calibration)
    np.testing.assert_allclose(res.depth, depth, rtol=1e-6)
    same = np.mean(res.source == np.where(index >= 0, owner[np.maximum(index, 0)], -1))
    assert same > 0.999


def test_a_common_change_of_world_frame_changes_nothing(street):
    rig, _frames, sims, poses = street
    scans = [s.points for s in sims]
    G = pose(123.0, -45.0, 2.0, yaw_deg=37.0)
    a = accumulate_scans(scans, poses, rig.calibration, reference=2)
    b = accumulate_scans(scans, G[None] @ poses, rig.calibration, reference=2)
    assert np.mean(a.depth == b.depth) > 0.999
    np.testing.assert_allclose(a.depth[b.depth > 0], b.depth[b.depth > 0], rtol=1e-6, atol=0)


def test_duplicate_scan_is_never_inconsistent(street):
    rig, _frames, sims, poses = street
    pts = sims[2].points
    res = accumulate_scans([pts, pts], [poses[2], poses[2]], rig.calibration, reference=1)
    np.testing.assert_array_equal(res.depth, project_points(pts, rig.calibration))
    # A copy can never be nearer than the point itself; it can be occluded (a see-through
    # point of the scan at a depth edge) but never inconsistent.
    assert res.counts.inconsistent == 0
    assert res.counts.occluded < 0.05 * res.counts.kept
    # Equal depth and coordinates: the smaller index wins, i.e. scan 0 where it was kept.
    assert np.mean(res.source[res.depth > 0] == 0) > 0.9


# -- constructed scenes: camera = sensor frame, simple pinhole ------------------------------------

# Principal point off the half-pixel grid so that no constructed point lands on a pixel border.
CX, CY = 80.2, 60.3
CALIB = Calibration(
    K=[[100.0, 0, CX], [0, 100.0, CY], [0, 0, 1]],
    T_cam_from_sensor=np.eye(4),
    width=160,
    height=120,
)


def pixels(pts):
    return np.rint(100 * pts[:, 0] / pts[:, 2] + CX), np.rint(100 * pts[:, 1] / pts[:, 2] + CY)


def near_foreground(pts, fg_pts, radius=1):
    """Reference occlusion test: a foreground pixel within ``radius`` (Chebyshev) of the
    point's pixel. The window radius of the defaults is rint(100 * 0.1 / z) clipped to
    1..8, i.e. 1 for z >= 6.7 m."""
    fg = project_points(fg_pts, CALIB) > 0
    grown = np.zeros_like(fg)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            grown |= np.roll(np.roll(fg, dy, axis=0), dx, axis=1)
    u, v = pixels(pts)
    inside = (u >= 0) & (u < 160) & (v >= 0) & (v < 120)
    out = np.zeros(pts.shape[0], bool)
    out[inside] = grown[v[inside].astype(int), u[inside].astype(int)]
    return out


def grid(x0, x1, y0, y1, z, step):
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step))
    return np.column_stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)])


def blocked_by(origin, pts, box):
    """Rows of ``pts`` whose segment from ``origin`` crosses the z-plane board ``box``
    (x0, x1, y0, y1, z) before reaching the point."""
    x0, x1, y0, y1, zb = box
    s = (zb - origin[2]) / (pts[:, 2] - origin[2])
    hx = origin[0] + s * (pts[:, 0] - origin[0])
    hy = origin[1] + s * (pts[:, 1] - origin[1])
    return (s > 0) & (s < 1) & (hx >= x0) & (hx <= x1) & (hy >= y0) & (hy <= y1)


def test_occlusion_drops_the_hidden_points_of_two_planes():
    board = (-0.5, 0.5, -0.5, 0.5, 5.0)  # 1 m board at 5 m in front of a wall at 20 m
    wall = grid(-12, 12, -9, 9, 20.0, 0.2)
    board_pts = grid(-0.5, 0.5, -0.5, 0.5, 5.0, 0.02)
    origin_t = np.zeros(3)
    own = np.vstack([board_pts, wall[~blocked_by(origin_t, wall, board)]])
    # Another scan 1.5 m to the side sees the wall behind the board.
    other_origin = np.array([1.5, 0.0, 0.0])
    seen_other = wall[~blocked_by(other_origin, wall, board)]
    other_local = seen_other - other_origin  # in its own sensor frame (same axes)
    poses = np.array([pose(), pose(*other_origin)])
    hidden = blocked_by(origin_t, seen_other, board)
    assert hidden.sum() > 300
    expected = near_foreground(seen_other, board_pts)
    assert np.all(expected[hidden])  # the reference drops every hidden point ...
    for fg in ("all", "own"):
        s = AccumulateSettings(occlusion_foreground=fg, consistency_rel=None)
        res = accumulate_scans([own, other_local], poses, CALIB, reference=0, settings=s)
        # ... and the filter drops exactly the reference's points.
        assert res.counts_per_scan[1].occluded == int(expected.sum())
        board_px = project_points(board_pts, CALIB) > 0
        assert np.all(np.abs(res.depth[board_px] - 5.0) < 1e-4)
        assert np.all(res.source[board_px] == 0)
    # Without the filter nothing is dropped (the nearer board still wins every pixel).
    raw = accumulate_scans([own, other_local], poses, CALIB, reference=0, settings=NO_FILTERS)
    assert raw.counts.occluded == 0 and raw.counts.kept == own.shape[0] + seen_other.shape[0]


def moved_box_scene():
    wall = grid(-12, 12, -9, 9, 20.0, 0.2)
    box_then = (-2.0, -1.0, -0.5, 0.5, 8.0)  # where the box was in the other scans
    box_now = (1.0, 2.0, -0.5, 0.5, 8.0)  # where it is at frame t
    o = np.zeros(3)
    then_pts = grid(*box_then[:4], 8.0, 0.02)
    now_pts = grid(*box_now[:4], 8.0, 0.02)
    own = np.vstack([now_pts, wall[~blocked_by(o, wall, box_now)]])
    other = np.vstack([then_pts, wall[~blocked_by(o, wall, box_then)]])
    return own, other, then_pts, now_pts


def test_moving_object_filter_drops_the_moved_box():
    own, other, then_pts, now_pts = moved_box_scene()
    poses = np.array([pose(), pose()])  # static ego, the box moved
    res = accumulate_scans([other, own, other], poses[[0, 0, 0]], CALIB, reference=1)
    then_px = project_points(then_pts, CALIB) > 0
    now_px = project_points(now_pts, CALIB) > 0
    # Where the box was, frame t sees the wall: the old box points are gone ...
    assert np.all(np.abs(res.depth[then_px] - 20.0) < 1e-3)
    # ... where it is now, the wall points of the other scans are hidden behind it.
    assert np.all(np.abs(res.depth[now_px] - 8.0) < 1e-3)
    other_wall = other[then_pts.shape[0] :]
    expected = near_foreground(other_wall, now_pts)
    assert np.all(expected[blocked_by(np.zeros(3), other_wall, (1.0, 2.0, -0.5, 0.5, 8.0))])
    for k in (0, 2):
        c = res.counts_per_scan[k]
        assert c.inconsistent == then_pts.shape[0]
        assert c.occluded == int(expected.sum())
    # Switched off, the old box stays in the map.
    off = AccumulateSettings(consistency_rel=None)
    res_off = accumulate_scans([other, own], poses, CALIB, reference=1, settings=off)
    assert np.all(np.abs(res_off.depth[then_px] - 8.0) < 1e-3)


def test_moving_mask_drops_other_scans_points_only():
    own, other, then_pts, _ = moved_box_scene()
    poses = np.array([pose(), pose()])
    then_px = project_points(then_pts, CALIB) > 0
    s = AccumulateSettings(consistency_rel=None)
    res = accumulate_scans([other, own], poses, CALIB, reference=1, settings=s, moving_mask=then_px)
    assert np.all(np.abs(res.depth[then_px] - 20.0) < 1e-3)
    assert res.counts_per_scan[0].masked >= then_pts.shape[0]
    assert res.counts_per_scan[1].masked == 0
    # Frame t's own points inside the mask stay.
    full = np.ones((120, 160), bool)
    res2 = accumulate_scans([other, own], poses, CALIB, reference=1, settings=s, moving_mask=full)
    np.testing.assert_array_equal(res2.depth, project_points(own, CALIB))


def test_hold_out_reference():
    own, other, _, _ = moved_box_scene()
    poses = np.array([pose(), pose()])
    res = accumulate_scans(
        [other, own], poses, CALIB, reference=1, settings=NO_FILTERS, hold_out_reference=True
    )
    assert not np.any(res.source == 1)
    assert res.counts_per_scan[1].kept == 0 and res.counts_per_scan[1].held_out == own.shape[0]
    np.testing.assert_array_equal(res.depth, project_points(other, CALIB))
    # With the occlusion test among the other scans, their wall points around the old box
    # (the box itself is nearer) are dropped, and nothing else.
    s = AccumulateSettings(consistency_rel=None)
    res = accumulate_scans(
        [other, own], poses, CALIB, reference=1, settings=s, hold_out_reference=True
    )
    n_box = 51 * 51
    assert res.counts_per_scan[0].occluded == int(
        near_foreground(other[n_box:], other[:n_box]).sum()
    )
    with pytest.raises(ParameterError, match="hold_out_reference"):
        accumulate_scans([other, own], poses, CALIB, reference=1, hold_out_reference=True)


def test_rotated_pose_is_applied():
    # The other scan's sensor is yawed by 30 deg: its points, moved back, land exactly on
    # frame t's own points.
    pts = grid(-3, 3, -2, 2, 10.0, 0.1)
    T = pose(0.3, -0.2, 0.1, yaw_deg=30.0)
    local = transform(np.linalg.inv(T), pts)
    res = accumulate_scans([np.zeros((0, 3)), local], np.array([np.eye(4), T]), CALIB, reference=0)
    np.testing.assert_allclose(res.depth, project_points(pts, CALIB), atol=1e-5)
    assert res.counts_per_scan[0].points == 0


def test_bad_arguments():
    pts = grid(-1, 1, -1, 1, 5.0, 0.1)
    two = np.array([np.eye(4), np.eye(4)])
    for kw, match in (
        ({"reference": 2}, "reference"),
        ({"reference": 0, "moving_mask": np.zeros((10, 10), bool)}, "--moving-mask: must have"),
        ({"reference": 0, "moving_mask": np.zeros((120, 160))}, "--moving-mask: must be bool"),
        ({"reference": 0, "settings": {"occlusion_rel": 0.2}}, "settings"),
    ):
        with pytest.raises(ParameterError, match=match):
            accumulate_scans([pts, pts], two, CALIB, **kw)
    with pytest.raises(ParameterError, match=r"--T-world-from-velo: must have shape \(2, 4, 4\)"):
        accumulate_scans([pts, pts], two[:1], CALIB, reference=0)
    with pytest.raises(ParameterError, match="--T-world-from-velo: holds NaN"):
        accumulate_scans([pts, pts], two * np.nan, CALIB, reference=0)
    with pytest.raises(ParameterError, match="last row 0 0 0 1"):
        accumulate_scans([pts, pts], two * 2, CALIB, reference=0)
    with pytest.raises(ParameterError, match=r"--scans\[1\]: must have shape \(N, C>=3\)"):
        accumulate_scans([pts, pts[:, :2]], two, CALIB, reference=0)
    with pytest.raises(ParameterError, match="at least one"):
        accumulate_scans([], np.zeros((0, 4, 4)), CALIB, reference=0)
    for bad in (
        {"occlusion_rel": -0.1},
        {"occlusion_foreground": "near"},
        {"footprint_m": 0},
        {"min_radius_px": 3, "max_radius_px": 2},
        {"max_depth": 0.05},
        {"pixel_offset": 0.5},
    ):
        with pytest.raises(ParameterError) as err:
            AccumulateSettings(**bad)
        assert err.value.param in bad  # named for the command line's option
