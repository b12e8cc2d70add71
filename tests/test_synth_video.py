"""Synthetic street videos: exact poses, LiDAR against depth, moving mask, stops, determinism,
variety, view-independent shading, the file layout."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest

from sparsetools.errors import OutputError, ParameterError
from sparsetools.io.calib import read_kitti_object_calib
from sparsetools.io.image import read_depth_png, read_image
from sparsetools.io.kitti import read_velodyne_bin
from sparsetools.io.poses import read_kitti_poses, read_pose_matrix, read_times
from sparsetools.synth.primitives import (
    SHAPE_BOX,
    SHAPE_CYLINDER,
    SHAPE_ELLIPSOID,
    Primitives,
    build_bvh,
    cast,
)
from sparsetools.synth.roads import Road
from sparsetools.synth.video import VideoSimulator, simulate_video
from sparsetools.synth.video_files import write_video
from sparsetools.synth.video_params import draw_sequence_params

SIZE = (256, 80)


def stopping_params(seed: int = 3):
    """Seed 3's street, driving at 6 m/s, braking at 0.2 s at 6 m/s^2: at rest from 1.2 s."""
    p = draw_sequence_params(seed, 0)
    drive = dataclasses.replace(
        p.drive, speed_mps=6.0, brake_time_s=0.2, deceleration_mps2=6.0, lane_change_to=-1
    )
    street = dataclasses.replace(p.street, moving_cars=4, pedestrians_per_100m=6.0)
    return dataclasses.replace(p, drive=drive, street=street)


@pytest.fixture(scope="module")
def moving():
    return simulate_video(3, n_frames=16, image_size=SIZE, lidar=False, params=stopping_params())


@pytest.fixture(scope="module")
def static():
    return simulate_video(1, n_frames=6, image_size=SIZE, static=True)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("video") / "v"
    summary = write_video(out, seed=5, sequences=2, n_frames=3, image_size=(128, 40))
    return out, summary


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _inv(T):
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


# -- poses ----------------------------------------------------------------------------------------
def test_poses_are_consistent(static, moving):
    for seq in (static, moving):
        assert np.array_equal(seq.frames[0].T_world_from_cam, np.eye(4))
        for f in seq.frames:
            assert np.allclose(
                f.T_world_from_velo, f.T_world_from_cam @ f.T_cam_from_velo, atol=1e-12
            )
            R = f.T_world_from_cam[:3, :3]
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        assert np.allclose(seq.times, np.arange(len(seq.frames)) / 10.0)


def test_mounting_matches_the_drawn_rig():
    """Flat straight road: the camera is camera_height_m above the road, looking
    camera_pitch_deg below the horizon; the LiDAR is above and behind it, axes level."""
    p = draw_sequence_params(4, 0)
    p = dataclasses.replace(p, road=Road(), drive=dataclasses.replace(p.drive, lane_change_to=-1))
    sim = VideoSimulator(4, 0, n_frames=2, image_size=SIZE, params=p, lidar=False)
    T = sim.T_scene_from_cam(0)
    assert T[2, 3] == pytest.approx(p.rig.camera_height_m)
    optical_axis = T[:3, 2]  # camera z in the scene (z up)
    assert math.degrees(-math.asin(optical_axis[2])) == pytest.approx(p.rig.camera_pitch_deg)
    velo_in_cam = sim.T_cam_from_velo[:3, 3]
    up_in_cam = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    forward_in_cam = T[:3, :3].T @ np.array([1.0, 0.0, 0.0])
    assert velo_in_cam @ up_in_cam == pytest.approx(p.rig.lidar_above_camera_m)
    assert velo_in_cam @ forward_in_cam == pytest.approx(-p.rig.camera_ahead_m)
    # LiDAR axes are the car's: level, x forward.
    R_scene_velo = T[:3, :3] @ sim.T_cam_from_velo[:3, :3]
    assert np.allclose(R_scene_velo, np.eye(3), atol=1e-12)
    # The ego drives along +x of the scene at its speed: frame 1 is 0.1 s * v further.
    step = sim.T_scene_from_cam(1)[:3, 3] - T[:3, 3]
    assert np.allclose(step, [0.1 * p.drive.speed_mps, 0.0, 0.0], atol=1e-9)


def test_pose_follows_slope_and_curve():
    p = draw_sequence_params(0, 0)
    road = Road(turn_start_m=0.0, turn_length_m=200.0, curvature_per_m=1 / 150, grade=0.05)
    drive = dataclasses.replace(p.drive, speed_mps=10.0, brake_time_s=math.inf, lane_change_to=-1)
    p = dataclasses.replace(p, road=road, drive=drive)
    sim = VideoSimulator(0, 0, n_frames=31, image_size=SIZE, params=p, lidar=False)
    base = [e.T_scene_from_base for e in sim.ego]
    # 3 s at 10 m/s: 30 m along the centre line of a 150 m radius, the heading turned 0.2 rad.
    assert sim.ego[30].s_m == pytest.approx(30.0)
    forward = base[30][:3, 0]
    assert math.atan2(forward[1], forward[0]) == pytest.approx(30.0 / 150.0, abs=1e-9)
    # Its position is the lane offset l left of the arc's point: radius 150 - l about (0, 150).
    l = p.street.lane_centre_m(p.drive.lane)
    assert math.hypot(base[30][0, 3], base[30][1, 3] - 150.0) == pytest.approx(150.0 - l)
    # On the ground plane z = 0.05 x: the base origin stays on it, its z axis is the normal.
    for T in base:
        assert T[2, 3] == pytest.approx(0.05 * T[0, 3], abs=1e-12)
        assert np.allclose(T[:3, 2], road.ground_normal, atol=1e-12)


def test_road_street_coordinates_round_trip():
    rng = np.random.default_rng(0)
    for road in (
        Road(),
        Road(turn_start_m=20.0, turn_length_m=60.0, curvature_per_m=1 / 130),
        Road(turn_start_m=5.0, turn_length_m=100.0, curvature_per_m=-1 / 300, grade=0.03),
    ):
        s = rng.uniform(-50.0, 200.0, 300)
        l = rng.uniform(-30.0, 30.0, 300)
        xy = np.array([road.point(a, b)[:2] for a, b in zip(s, l, strict=True)])
        s2, l2 = road.to_street(xy[:, 0], xy[:, 1])
        assert np.allclose(s2, s, atol=1e-9) and np.allclose(l2, l, atol=1e-9)


# -- LiDAR ----------------------------------------------------------------------------------------
def _inverse_depth_lookup(depth, u, v):
    """Bilinear interpolation of 1/depth (exact on planes) where the 2x2 block is continuous."""
    h, w = depth.shape
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    u0, v0, fu, fv = u0[ok], v0[ok], (u - np.floor(u))[ok], (v - np.floor(v))[ok]
    q = np.stack([depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]])
    smooth = (q > 0).all(axis=0) & (q.max(axis=0) <= 1.03 * q.min(axis=0))
    inv = 1.0 / np.where(q > 0, q, 1.0)
    i = (inv[0] * (1 - fu) + inv[1] * fu) * (1 - fv) + (inv[2] * (1 - fu) + inv[3] * fu) * fv
    out = np.zeros(u.shape)
    mask = np.zeros(u.shape, dtype=bool)
    out[ok] = np.where(smooth, 1.0 / i, 0.0)
    mask[ok] = smooth
    return out, mask


@pytest.fixture(scope="module")
def static_curved_slope():
    """Seed 7's street turned into a left curve of radius 150 m from s = 0 on a 3.4 deg grade,
    driven at 12.5 m/s: the camera yaws 2.4 deg and pitches with the grade in 5 frames."""
    p = draw_sequence_params(7, 0)
    road = Road(turn_start_m=0.0, turn_length_m=100.0, curvature_per_m=1 / 150, grade=0.06)
    p = dataclasses.replace(p, road=road)
    seq = simulate_video(7, n_frames=6, image_size=SIZE, static=True, params=p)
    R = seq.frames[5].T_world_from_cam[:3, :3]
    assert math.degrees(math.acos((np.trace(R) - 1) / 2)) > 2.0
    return seq


@pytest.mark.parametrize(("which", "k"), [("flat", 0), ("flat", 3), ("flat", 5), ("curved", 5)])
def test_lidar_of_frame_k_lands_on_frame_0_depth(static, static_curved_slope, which, k):
    """Static scene: scan k moved with the true poses into frame 0's camera meets frame 0's
    dense depth (range noise sigma 1.5 cm) where frame 0 sees the point; where it does not,
    frame 0 sees something nearer (an occluder), never something farther (a pose error would
    put points in front of the surfaces)."""
    seq = static if which == "flat" else static_curved_slope
    f0, fk = seq.frames[0], seq.frames[k]
    assert len(fk.points) > 60_000
    T = _inv(f0.T_world_from_cam) @ fk.T_world_from_velo
    P = fk.points[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    front = P[:, 2] > 1.0
    K = seq.K
    z = P[front, 2]
    u = K[0, 0] * P[front, 0] / z + K[0, 2]
    v = K[1, 1] * P[front, 1] / z + K[1, 2]
    gt, ok = _inverse_depth_lookup(f0.depth.astype(np.float64), u, v)
    assert ok.sum() > 1500
    err = gt[ok] - z[ok]
    tol = 0.06 + 0.01 * z[ok]
    agree = np.abs(err) <= tol
    assert np.mean(err > tol) < 0.005  # in front of what frame 0 sees: (almost) never
    assert agree.mean() > (0.9 if which == "flat" else 0.6)
    assert np.median(np.abs(err[agree])) < 0.025
    if k:  # the ego moved: this is not the scan of frame 0 again
        assert np.linalg.norm(fk.T_world_from_velo[:3, 3] - f0.T_world_from_velo[:3, 3]) > 2.0


def test_scan_order_and_rings(static):
    f = static.frames[2]
    az = np.mod(np.degrees(np.arctan2(f.points[:, 1], f.points[:, 0])), 360.0)
    recovered = np.concatenate([[0], np.cumsum(np.diff(az) < -90.0)])
    assert np.array_equal(recovered, f.ring) and f.ring.max() == 63
    assert f.points[:, 3].min() >= 0 and f.points[:, 3].max() <= 1


# -- moving objects -------------------------------------------------------------------------------
def _pixel_rays(K, h, w, offsets):
    """(S, H*W, 3) camera rays (unit z) through pixel centres shifted by each offset."""
    out = []
    for du, dv in offsets:
        v, u = np.mgrid[0:h, 0:w].astype(np.float64)
        x = (u + du - K[0, 2]) / K[0, 0]
        y = (v + dv - K[1, 2]) / K[1, 1]
        out.append(np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3))
    return np.stack(out)


def _ray_meets_box(origin, d, lo, hi):
    """(N,) rays origin + t d (t > 0) that intersect the box [lo, hi] (reference slab test)."""
    tn = np.full(d.shape[0], -np.inf)
    tf = np.full(d.shape[0], np.inf)
    for a in range(3):
        da = d[:, a]
        inv = 1.0 / np.where(da != 0, da, 1e-300)
        t1 = (lo[a] - origin[a]) * inv
        t2 = (hi[a] - origin[a]) * inv
        tn = np.maximum(tn, np.minimum(t1, t2))
        tf = np.minimum(tf, np.maximum(t1, t2))
    return (tn <= tf) & (tf > 0)


def _may_be_in_view(actor, frame, K, w, h) -> bool:
    """False when the actor's box projects wholly outside the image (all corners in front)."""
    hx, hy, hz = actor.half_extents
    corners = np.array([[x, y, z, 1.0] for x in (-hx, hx) for y in (-hy, hy) for z in (0, 2 * hz)])
    c = (_inv(frame.T_world_from_cam) @ actor.T_world_from_actor @ corners.T).T
    if np.any(c[:, 2] <= 0.1):
        return bool(np.any(c[:, 2] > 0.1))
    u = K[0, 0] * c[:, 0] / c[:, 2] + K[0, 2]
    v = K[1, 1] * c[:, 1] / c[:, 2] + K[1, 2]
    return bool(u.max() >= -1 and u.min() <= w and v.max() >= -1 and v.min() <= h)


def test_moving_mask_covers_moving_actors_and_nothing_static(moving):
    K = moving.K
    h, w = moving.height, moving.width
    offsets = [(0, 0), (-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)]
    rays = _pixel_rays(K, h, w, offsets)
    seen = 0
    for f in moving.frames:
        movers = [a for a in f.actors if a.moving]
        assert movers
        movers = [a for a in movers if _may_be_in_view(a, f, K, w, h)]
        # (1) Pixels whose surface point lies inside a moving actor's box are masked.
        d = f.depth.astype(np.float64).reshape(-1)
        pts = rays[0] * d[:, None]
        inside = np.zeros(h * w, dtype=bool)
        reach = np.zeros(h * w, dtype=bool)
        for a in movers:
            T = _inv(a.T_world_from_actor) @ f.T_world_from_cam
            q = pts @ T[:3, :3].T + T[:3, 3]
            hx, hy, hz = a.half_extents + 1e-3
            inside |= (
                (d > 0)
                & (np.abs(q[:, 0]) <= hx)
                & (np.abs(q[:, 1]) <= hy)
                & (q[:, 2] > 0.03)
                & (q[:, 2] <= 2 * hz)
            )
            # (2) Every masked pixel has a sample ray that meets some moving actor's box.
            o = T[:3, 3]
            lo = np.array([-hx, -hy, -1e-3])
            hi = np.array([hx, hy, 2 * hz])
            for s in range(len(offsets)):
                reach |= _ray_meets_box(o, rays[s] @ T[:3, :3].T, lo, hi)
        mask = f.moving_mask.reshape(-1)
        assert np.all(mask[inside])
        assert not np.any(mask & ~reach)
        seen += int(inside.sum())
    assert seen > 200  # the moving cars and people are really in view
    # Static actors (standing people) exist and are never masked by being in the list.
    assert any(not a.moving for a in moving.frames[0].actors)


def test_stopped_frames_are_identical_where_nothing_moves(moving):
    speeds = np.array([f.speed_mps for f in moving.frames])
    stopped = np.nonzero(speeds == 0)[0]
    assert stopped.size >= 3 and stopped[0] == 12
    assert np.all(speeds[:2] > 5.0)
    for a, b in itertools.pairwise(stopped):
        fa, fb = moving.frames[a], moving.frames[b]
        assert np.array_equal(fa.T_world_from_cam, fb.T_world_from_cam)
        still = ~(fa.moving_mask | fb.moving_mask)
        assert still.mean() > 0.9
        assert np.array_equal(fa.image[still], fb.image[still])
        assert np.array_equal(fa.depth[still], fb.depth[still])
        # Something does move: the masked pixels change.
        changed = np.any(fa.image != fb.image, axis=2)
        assert changed.any() and not np.any(changed & still)


def test_static_mode_has_no_moving_objects(static):
    for f in static.frames:
        assert not f.moving_mask.any()
        assert not any(a.moving for a in f.actors)


# -- view-independent shading ---------------------------------------------------------------------
def test_warp_with_true_depth_and_pose_reproduces_the_frame(static):
    """Frame 1 warped into frame 0 with frame 0's true depth and the true relative pose equals
    frame 0 up to interpolation error where the point is visible in both."""
    import cv2

    f0, f1 = static.frames[0], static.frames[1]
    K = static.K
    h, w = f0.depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    d = f0.depth.astype(np.float64)
    X = np.stack([(u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d, d], -1)
    T = _inv(f1.T_world_from_cam) @ f0.T_world_from_cam
    Y = X @ T[:3, :3].T + T[:3, 3]
    z1 = Y[..., 2]
    u1 = (K[0, 0] * Y[..., 0] / np.where(z1 > 0, z1, 1) + K[0, 2]).astype(np.float32)
    v1 = (K[1, 1] * Y[..., 1] / np.where(z1 > 0, z1, 1) + K[1, 2]).astype(np.float32)
    inside = (d > 0) & (z1 > 0.5) & (u1 >= 0) & (u1 <= w - 1) & (v1 >= 0) & (v1 <= h - 1)
    warped = cv2.remap(f1.image.astype(np.float32), u1, v1, cv2.INTER_LINEAR)
    depth1 = cv2.remap(f1.depth, u1, v1, cv2.INTER_NEAREST)
    visible = inside & (np.abs(depth1 - z1) < 0.02 * z1)
    assert visible.mean() > 0.5
    err = np.abs(warped - f0.image.astype(np.float32)).mean(axis=2)[visible]
    unwarped = np.abs(f1.image.astype(np.float32) - f0.image).mean(axis=2)[visible]
    assert np.median(err) < 0.6 and np.percentile(err, 75) < 2.0
    assert np.mean(err) < 0.4 * np.mean(unwarped)  # the motion is real


# -- determinism, independence --------------------------------------------------------------------
def test_frame_does_not_depend_on_sequence_length():
    a = VideoSimulator(2, 1, n_frames=3, image_size=(96, 32)).frame(2)
    b = VideoSimulator(2, 1, n_frames=6, image_size=(96, 32)).frame(2)
    assert np.array_equal(a.image, b.image) and np.array_equal(a.depth, b.depth)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.moving_mask, b.moving_mask)
    assert np.array_equal(a.T_world_from_cam, b.T_world_from_cam)


def test_same_seed_same_bytes_for_any_workers(written, tmp_path):
    out, _ = written
    again = tmp_path / "again"
    write_video(again, seed=5, sequences=2, n_frames=3, image_size=(128, 40), workers=2)
    assert _files(again) == _files(out)
    other = tmp_path / "other"
    write_video(other, seed=6, sequences=1, n_frames=1, image_size=(128, 40))
    name = "seq_0000/image_2/0000000000.png"
    assert (other / name).read_bytes() != (out / name).read_bytes()


def test_image_noise_is_small_and_per_frame():
    clean = simulate_video(0, n_frames=2, image_size=(64, 24), lidar=False)
    noisy = simulate_video(0, n_frames=2, image_size=(64, 24), lidar=False, image_noise=2.0)
    diff = noisy.frames[0].image.astype(float) - clean.frames[0].image
    assert 1.0 < diff.std() < 3.0 and abs(diff.mean()) < 0.5
    d1 = noisy.frames[1].image.astype(float) - clean.frames[1].image
    assert not np.array_equal(diff, d1)


# -- variety --------------------------------------------------------------------------------------
def test_variety_between_seeds_is_recorded(written):
    params = [draw_sequence_params(seed, 0) for seed in range(16)]
    for field in ("camera_height_m", "camera_pitch_deg"):
        values = [getattr(p.rig, field) for p in params]
        assert len(set(values)) == 16 and np.std(values) > 0.1
    assert 1.2 < min(p.rig.camera_height_m for p in params)
    assert max(p.rig.camera_height_m for p in params) < 2.0
    assert len({p.road.grade for p in params}) > 5
    assert any(p.road.curved for p in params) and any(not p.road.curved for p in params)
    assert {p.street.lanes_per_direction for p in params} == {1, 2}
    assert any(p.drive.lane_change_to >= 0 for p in params)
    assert any(math.isfinite(p.drive.brake_time_s) for p in params)
    assert len({p.street.building_height_m for p in params}) == 16
    assert len({p.light.sun_azimuth_deg for p in params}) == 16
    assert len({p.light.sky_zenith for p in params}) > 1
    # Sequences of one seed differ too, and scene.json records every drawn parameter.
    out, _ = written
    for i in range(2):
        meta = json.loads((out / f"seq_{i:04d}/scene.json").read_text())
        assert meta["params"] == draw_sequence_params(5, i).to_dict()
        assert meta["params"]["rig"]["camera_height_m"] > 1.0
        assert {"curvature_per_m", "grade", "slope_deg"} <= set(meta["params"]["road"])
        assert meta["street"]["object_counts"]["building"] > 5
    assert draw_sequence_params(5, 0) != draw_sequence_params(5, 1)


# -- files ----------------------------------------------------------------------------------------
def test_layout_poses_files_and_calibration(written):
    import cv2

    out, summary = written
    names = set(_files(out))
    assert summary["files_written"] == len(names)
    assert "video.json" in names
    for seq in ("seq_0000", "seq_0001"):
        for rel in ("poses.txt", "poses_velodyne.txt", "times.txt", "scene.json"):
            assert f"{seq}/{rel}" in names
        for k in range(3):
            stem = f"{k:010d}"
            for folder, ext in (
                ("image_2", "png"),
                ("velodyne", "bin"),
                ("depth_gt", "png"),
                ("moving_mask", "png"),
                ("calib", "txt"),
                ("poses", "txt"),
                ("velodyne_ring", "npy"),
            ):
                assert f"{seq}/{folder}/{stem}.{ext}" in names
        root = out / seq
        poses = read_kitti_poses(root / "poses.txt")
        velo = read_kitti_poses(root / "poses_velodyne.txt")
        assert poses.shape == (3, 4, 4) and np.array_equal(poses[0], np.eye(4))
        calib = read_kitti_object_calib(root / "calib/0000000000.txt")
        for k in range(3):
            assert np.array_equal(read_pose_matrix(root / f"poses/{k:010d}.txt"), poses[k])
            assert np.allclose(velo[k], poses[k] @ calib.T_cam_from_sensor, atol=1e-9)
        assert np.allclose(read_times(root / "times.txt"), [0.0, 0.1, 0.2])
        # Files hold what the in-memory API gives.
        seq_mem = simulate_video(5, sequence=int(seq[-1]), n_frames=3, image_size=(128, 40))
        f = seq_mem.frames[2]
        assert np.array_equal(read_image(root / "image_2/0000000002.png"), f.image)
        assert np.array_equal(read_velodyne_bin(root / "velodyne/0000000002.bin"), f.points)
        depth = read_depth_png(root / "depth_gt/0000000002.png")
        has = f.depth > 0
        assert np.array_equal(depth > 0, has)
        assert np.abs(depth[has] - f.depth[has]).max() <= 0.5 / 256 + 1e-6
        mask = cv2.imread(str(root / "moving_mask/0000000002.png"), cv2.IMREAD_UNCHANGED)
        assert mask.dtype == np.uint8 and mask.shape == f.depth.shape
        assert set(np.unique(mask)) <= {0, 255}
        assert np.array_equal(mask == 255, f.moving_mask)
        assert np.allclose(calib.P[:, :3], f.K) and np.allclose(
            calib.T_cam_from_sensor, f.T_cam_from_velo, atol=1e-11
        )
        assert np.array_equal(poses[2], f.T_world_from_cam)


def test_refuses_non_empty_folder_and_bad_arguments(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(OutputError):
        write_video(tmp_path / "full", n_frames=1, image_size=(32, 16))
    for bad in (
        dict(n_frames=0),
        dict(seed=-1),
        dict(sequences=0),
        dict(image_size=(8, 8)),
        dict(antialias=5),
        dict(image_noise=-1.0),
        dict(workers=0),
    ):
        with pytest.raises(ParameterError):
            write_video(tmp_path / "x", **{"n_frames": 1, "image_size": (32, 16), **bad})
    assert not (tmp_path / "x").exists()
    with pytest.raises(ParameterError):
        VideoSimulator(0, n_frames=2, image_size=(32, 16), lidar=False).frame(2)


# -- ray casting ----------------------------------------------------------------------------------
def _random_primitives(n: int, seed: int) -> Primitives:
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        q = rng.normal(size=4)
        w, x, y, z = q / np.linalg.norm(q)
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
            ]
        )
        shape = (SHAPE_BOX, SHAPE_ELLIPSOID, SHAPE_CYLINDER)[i % 3]
        half = rng.uniform(0.3, 2.0, 3)
        if shape == SHAPE_CYLINDER:
            half[1] = half[0]
        rows.append(
            (
                rng.uniform(-15, 15, 3) + np.array([0.0, 0.0, 20.0]),
                R,
                half,
                shape,
                0,
                i,
                (1, 1, 1),
                0.5,
                False,
            )
        )
    return Primitives.from_rows(rows)


def _inside(prims: Primitives, p: np.ndarray) -> np.ndarray:
    """(M, P) point-in-primitive test of points p (M, 3): the reference for the kernel."""
    q = np.einsum("pji,mpj->mpi", prims.rotation, p[:, None, :] - prims.centre[None])
    h = prims.half[None]
    box = np.all(np.abs(q) <= h, axis=2)
    ell = ((q / h) ** 2).sum(axis=2) <= 1.0
    cyl = (q[..., 0] ** 2 + q[..., 1] ** 2 <= h[..., 0] ** 2) & (np.abs(q[..., 2]) <= h[..., 2])
    return np.select([prims.shape == SHAPE_BOX, prims.shape == SHAPE_ELLIPSOID], [box, ell], cyl)


def test_cast_matches_ray_marching_reference():
    prims = _random_primitives(24, 0)
    rng = np.random.default_rng(1)
    # Rays towards random primitives (jittered by up to their size) and some at random.
    aim = prims.centre[rng.integers(0, len(prims), 300)] + rng.normal(size=(300, 3)) * 1.5
    aim[::4] = rng.normal(size=(75, 3)) * (5.0, 5.0, 1.0) + (0, 0, 20)
    dirs = aim / np.linalg.norm(aim, axis=1, keepdims=True)
    origin = np.zeros(3)
    hits = cast(origin, dirs, [build_bvh(prims)])
    step = 0.002
    t = np.arange(0.0, 45.0, step)
    radius = np.linalg.norm(prims.half, axis=1)
    n_hit = 0
    for i in range(0, 300, 2):
        # Only primitives whose bounding sphere the ray passes can contain its points.
        along = prims.centre @ dirs[i]
        miss = np.linalg.norm(prims.centre - along[:, None] * dirs[i], axis=1)
        cand = np.nonzero((miss <= radius) & (along + radius > 0))[0]
        sub = Primitives(**{k: getattr(prims, k)[cand] for k in Primitives.__dataclass_fields__})
        inside = _inside(sub, dirs[i] * t[:, None]).any(axis=1) if cand.size else t < 0
        if inside.any():
            first = t[np.argmax(inside)]
            assert hits.index[i] >= 0 and abs(hits.t[i] - first) <= step + 1e-9
            assert _inside(prims, (dirs[i] * (hits.t[i] + 1e-6))[None])[0, hits.index[i]]
            n_hit += 1
        else:
            assert hits.index[i] == -1 and np.isinf(hits.t[i])
    assert 25 < n_hit < 150


def test_bvh_equals_brute_force_and_ground_plane():
    prims = _random_primitives(300, 2)
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(5000, 3))
    origin = np.array([0.5, -0.3, 19.0])
    normal = np.array([0.0, 0.0, 1.0])
    tree = cast(origin, dirs, [build_bvh(prims)], ground=(normal, 10.0), t_max=60.0)
    flat = cast(origin, dirs, [build_bvh(prims, leaf_size=300)], ground=(normal, 10.0), t_max=60.0)
    median = cast(
        origin, dirs, [build_bvh(prims, split="median")], ground=(normal, 10.0), t_max=60.0
    )
    assert np.array_equal(tree.index, flat.index) and np.array_equal(tree.t, flat.t)
    assert np.array_equal(median.index, flat.index) and np.array_equal(median.t, flat.t)
    assert (tree.index >= 0).sum() > 1000
    ground = tree.index == -2
    assert ground.any()
    assert np.allclose((origin + dirs[ground] * tree.t[ground, None])[:, 2], 10.0)
    missed = tree.index == -1
    assert np.all(np.isinf(tree.t[missed]))
    down = dirs[missed, 2] < 0  # a ray down that misses meets the plane beyond t_max
    assert np.all(-9.0 / dirs[missed][down, 2] > 60.0)
    # Two sets: indices of the second count on from the first.
    a, b = _random_primitives(5, 4), _random_primitives(7, 5)
    both = cast(origin, dirs, [build_bvh(a), build_bvh(b)])
    joint = cast(origin, dirs, [build_bvh(Primitives.concat([a, b]))])
    assert np.array_equal(both.index, joint.index) and np.allclose(both.t, joint.t)
