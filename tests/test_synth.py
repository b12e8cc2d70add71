"""Synthetic scene generator: determinism, sensor/ground-truth consistency, file formats."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from sparsetools.calibration import Calibration
from sparsetools.errors import OutputError, ParameterError
from sparsetools.io.calib import read_json_calib, read_kitti_object_calib
from sparsetools.io.image import read_depth_png, read_image
from sparsetools.io.kitti import read_velodyne_bin
from sparsetools.io.nuscenes import RADAR_FIELDS, RadarFilter, read_radar_pcd
from sparsetools.synth import (
    BoxSet,
    Rig,
    backscatter,
    cast_rays,
    generate_scene,
    generate_underwater,
    light_cone,
    simulate_frame,
)
from sparsetools.synth.rig import KITTI_K

# Small but not tiny: 1/4 of KITTI's width keeps the whole module well under 30 s.
OPTS = dict(seed=3, frames=2, width=310, height=94, underwater_frames=12, underwater_size=(64, 48))
F = {name: i for i, name in enumerate(RADAR_FIELDS)}


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("synth") / "scene"
    done = []
    summary = generate_scene(out, progress=done.append, **OPTS)
    assert done == [1, 2]
    return out, summary


def _files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()
    }


def _scene_json(out: Path) -> dict:
    return json.loads((out / "scene.json").read_text())


# -- layout, arguments, determinism ------------------------------------------------------------
def test_layout_and_summary(scene):
    out, summary = scene
    names = set(_files(out))
    for stem in ("000000", "000001"):
        for rel in (
            f"image_2/{stem}.png",
            f"velodyne/{stem}.bin",
            f"velodyne_ring/{stem}.npy",
            f"calib/{stem}.txt",
            f"depth_gt/{stem}.png",
            f"radar/{stem}.pcd",
            f"calib_radar/{stem}.json",
        ):
            assert rel in names
        for k in range(5):
            assert f"radar/{stem}_sweep{k}.pcd" in names
    assert {f"underwater/seafloor/{i:06d}.png" for i in range(12)} <= names
    assert {f"underwater/water/{i:06d}.png" for i in range(8)} <= names
    assert {"underwater/albedo.png", "underwater/truth.json", "scene.json"} <= names
    assert not any(".tmp-" in n for n in names)
    assert summary["files_written"] == len(names)
    assert summary["frames"] == 2 and summary["image_size"] == "310x94"
    meta = _scene_json(out)
    assert meta["seed"] == 3 and meta["frames"] == 2 and meta["stems"] == ["000000", "000001"]
    assert len(meta["rig"]["lidar"]["laser_elevations_deg"]) == 64
    assert meta["lidar_points"] == summary["lidar_points"]
    # The ego drives 1 m along +x per frame.
    poses = np.array(meta["poses"]["T_world_from_velo"])
    assert np.allclose(poses[1, :3, 3] - poses[0, :3, 3], [1.0, 0.0, 0.0])
    assert image_shape(out / "image_2/000000.png") == (94, 310, 3)


def image_shape(path: Path) -> tuple[int, ...]:
    return read_image(path).shape


def test_same_seed_same_bytes_and_overwrite(scene, tmp_path):
    out, _ = scene
    again = tmp_path / "again"
    generate_scene(again, **OPTS)
    assert _files(again) == _files(out)
    # A non-empty folder is refused unless overwrite; overwriting gives the same bytes.
    with pytest.raises(OutputError):
        generate_scene(again, **OPTS)
    generate_scene(again, overwrite=True, **OPTS)
    assert _files(again) == _files(out)


def test_other_seed_other_scene(scene, tmp_path):
    out, _ = scene
    other = tmp_path / "other"
    generate_scene(other, **{**OPTS, "seed": 4, "frames": 1, "underwater_frames": 0})
    assert (other / "image_2/000000.png").read_bytes() != (out / "image_2/000000.png").read_bytes()
    assert not (other / "underwater").exists()


def test_frame_does_not_depend_on_sequence(scene):
    """Frame 1 simulated alone equals frame 1 of the generated sequence (worker-order free)."""
    out, _ = scene
    f = simulate_frame(3, 1, rig=Rig.kitti(310, 94))
    assert np.array_equal(f.image, read_image(out / "image_2/000001.png"))
    assert np.array_equal(f.points, read_velodyne_bin(out / "velodyne/000001.bin"))
    assert np.array_equal(f.ring, np.load(out / "velodyne_ring/000001.npy"))


@pytest.mark.parametrize(
    "bad",
    [
        dict(frames=0),
        dict(frames=1.5),
        dict(seed=-1),
        dict(seed=True),
        dict(width=8),
        dict(height=0),
        dict(underwater_frames=-1),
        dict(underwater_size=(4, 4)),
        dict(underwater_size=(64,)),
        dict(underwater_size=7),
    ],
)
def test_bad_arguments(tmp_path, bad):
    with pytest.raises(ParameterError):
        generate_scene(tmp_path / "x", **{**OPTS, **bad})
    assert not (tmp_path / "x").exists()


def test_output_is_a_file(tmp_path):
    target = tmp_path / "file"
    target.write_text("x")
    with pytest.raises(OutputError):
        generate_scene(target, **OPTS)


# -- calibration -------------------------------------------------------------------------------
def test_rig_intrinsics_follow_kitti():
    full = Rig.kitti()
    assert np.array_equal(full.K, KITTI_K)
    assert np.array_equal(full.P, np.hstack([KITTI_K, np.zeros((3, 1))]))
    # Half width with round(375 / 2) rows is exactly Calibration.resized(0.5).
    kitti = Calibration(K=KITTI_K, T_cam_from_sensor=np.eye(4), width=1242, height=375)
    half = kitti.resized(0.5)
    assert np.allclose(Rig.kitti(half.width, half.height).K, half.K)
    # Another height crops or extends evenly: the principal point stays in the middle band.
    tall = Rig.kitti(621, 250).K
    assert tall[0, 0] == half.K[0, 0] and tall[1, 2] == pytest.approx(half.K[1, 2] + 31.0)


def test_written_calibrations(scene):
    out, _ = scene
    calib = read_kitti_object_calib(out / "calib/000000.txt")
    rig = Rig.kitti(310, 94)
    assert np.allclose(calib.P, rig.P)
    T = calib.T_cam_from_sensor
    # Velodyne x (forward) -> camera z, y (left) -> -x, z (up) -> -y.
    assert np.allclose(T[:3, :3] @ [1, 0, 0], [0, 0, 1])
    assert np.allclose(T[:3, :3] @ [0, 1, 0], [-1, 0, 0])
    assert np.allclose(T[:3, :3] @ [0, 0, 1], [0, -1, 0])
    # Camera 1.65 m above ground, 0.08 m below and 0.27 m ahead of the Velodyne at 1.73 m.
    cam_in_velo = -T[:3, :3].T @ T[:3, 3]
    assert np.allclose(cam_in_velo, [0.27, 0.0, -0.08])
    radar = read_json_calib(out / "calib_radar/000000.json")
    assert (radar.width, radar.height) == (310, 94)
    T_velo_from_radar = np.linalg.inv(T) @ radar.T_cam_from_sensor
    assert np.allclose(T_velo_from_radar[:3, :3], np.eye(3))
    assert np.allclose(T_velo_from_radar[:3, 3], [2.5, 0.0, 0.5 - 1.73])


# -- LiDAR -------------------------------------------------------------------------------------
def _bilinear_inverse_depth(depth: np.ndarray, u: np.ndarray, v: np.ndarray):
    """GT depth at sub-pixel (u, v) by bilinear interpolation of 1/depth (exact on planes).

    Returns depth and a mask of points whose 2x2 neighbourhood is valid and continuous.
    """
    h, w = depth.shape
    u0 = np.floor(u).astype(int)
    v0 = np.floor(v).astype(int)
    ok = (u0 >= 0) & (v0 >= 0) & (u0 + 1 < w) & (v0 + 1 < h)
    u0, v0, fu, fv = u0[ok], v0[ok], (u - np.floor(u))[ok], (v - np.floor(v))[ok]
    quad = np.stack([depth[v0, u0], depth[v0, u0 + 1], depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]])
    valid = (quad > 0).all(axis=0)
    inv = np.where(quad > 0, 1.0 / np.where(quad > 0, quad, 1.0), 0.0)
    smooth = valid & (quad.max(axis=0) <= 1.03 * quad.min(axis=0))
    i = (inv[0] * (1 - fu) + inv[1] * fu) * (1 - fv) + (inv[2] * (1 - fu) + inv[3] * fu) * fv
    out = np.zeros(u.shape)
    mask = np.zeros(u.shape, dtype=bool)
    out[ok] = np.where(smooth, 1.0 / np.where(smooth, i, 1.0), 0.0)
    mask[ok] = smooth
    return out, mask


@pytest.mark.parametrize("stem", ["000000", "000001"])
def test_lidar_projects_onto_ground_truth_depth(scene, stem):
    """Points projected with the written calib (P2 R0_rect Tr) agree with the dense GT depth."""
    out, _ = scene
    points = read_velodyne_bin(out / f"velodyne/{stem}.bin")
    values = {}
    for line in (out / f"calib/{stem}.txt").read_text().splitlines():
        key, _, rest = line.partition(":")
        values[key] = np.array(rest.split(), dtype=float)
    P2 = values["P2"].reshape(3, 4)
    R0 = np.eye(4)
    R0[:3, :3] = values["R0_rect"].reshape(3, 3)
    Tr = np.vstack([values["Tr_velo_to_cam"].reshape(3, 4), [0, 0, 0, 1]])
    x = np.c_[points[:, :3], np.ones(len(points))] @ (P2 @ R0 @ Tr).T
    z = x[:, 2]
    front = z > 1.0
    u, v, z = x[front, 0] / z[front], x[front, 1] / z[front], z[front]
    depth = read_depth_png(out / f"depth_gt/{stem}.png").astype(np.float64)
    gt, ok = _bilinear_inverse_depth(depth, u, v)
    assert ok.sum() > 2000
    err = np.abs(gt[ok] - z[ok])
    assert np.median(err) < 0.05
    assert np.mean(err < 0.1 + 0.01 * z[ok]) > 0.95
    # Nearest-pixel lookup (the usual projection) agrees too, if less tightly on slanted road.
    ui, vi = np.rint(u).astype(int), np.rint(v).astype(int)
    inside = (ui >= 0) & (ui < depth.shape[1]) & (vi >= 0) & (vi < depth.shape[0])
    near = depth[vi[inside], ui[inside]]
    has = near > 0
    assert np.median(np.abs(near[has] - z[inside][has])) < 0.1


def test_scan_order_gives_64_rings(scene):
    out, _ = scene
    meta = _scene_json(out)
    elevations = np.array(meta["rig"]["lidar"]["laser_elevations_deg"])
    assert np.all(np.diff(elevations) < 0)
    assert elevations[0] == pytest.approx(2.0) and elevations[-1] == pytest.approx(-24.8)
    upper, lower = -np.diff(elevations[:32]), -np.diff(elevations[32:])
    assert upper.max() < lower.min()  # upper block finer than the lower block
    for stem in ("000000", "000001"):
        points = read_velodyne_bin(out / f"velodyne/{stem}.bin")
        ring = np.load(out / f"velodyne_ring/{stem}.npy")
        assert ring.dtype == np.uint8 and ring.shape == (len(points),)
        # As on real KITTI scans: each laser starts straight ahead, so the seam is at 0 deg.
        az = np.mod(np.degrees(np.arctan2(points[:, 1], points[:, 0])), 360.0)
        recovered = np.concatenate([[0], np.cumsum(np.diff(az) < -90.0)])
        assert recovered.max() + 1 == 64
        assert np.array_equal(recovered, ring)
        # Each point lies on its laser's cone (noise is along the ray).
        el = np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))
        assert np.abs(el - elevations[ring]).max() < 0.01
        per_ring = np.array([np.median(el[ring == r]) for r in range(64)])
        assert np.all(np.diff(per_ring) < 0)
        # Dense scan: most of the 64 x 2000 rays return; reflectance within [0, 1].
        assert 100_000 < len(points) <= 128_000
        assert points[:, 3].min() >= 0 and points[:, 3].max() <= 1
        r = np.linalg.norm(points[:, :3], axis=1)
        assert r.max() <= 120.1 and r.min() >= 0.9


def test_lidar_reflectance_by_material(scene):
    """Lane markings are bright, asphalt dark: ground points split by the world y of the point."""
    out, _ = scene
    meta = _scene_json(out)
    points = read_velodyne_bin(out / "velodyne/000000.bin")
    origin = np.array(meta["poses"]["T_world_from_velo"][0])[:3, 3]
    world = points[:, :3] + origin
    ground = np.abs(world[:, 2]) < 0.05
    on_edge_line = ground & (np.abs(np.abs(world[:, 1]) - 3.5) < 0.04)
    asphalt = (
        ground
        & (np.abs(world[:, 1]) > 0.3)
        & (np.abs(np.abs(world[:, 1]) - 3.5) > 0.3)
        & (np.abs(world[:, 1]) < 5.5)
    )
    assert on_edge_line.sum() > 20 and asphalt.sum() > 1000
    assert np.median(points[on_edge_line, 3]) > 0.5 > 0.2 > np.median(points[asphalt, 3])


# -- radar -------------------------------------------------------------------------------------
def _box_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) distance from points to the nearest box surface (inside points: to the nearest face)."""
    outside = np.maximum(np.maximum(lo[None] - p[:, None], p[:, None] - hi[None]), 0.0)
    d_out = np.linalg.norm(outside, axis=2)
    inside = np.minimum(p[:, None] - lo[None], hi[None] - p[:, None]).min(axis=2)
    d = np.where(inside > 0, inside, d_out)
    return d.min(axis=1)


def test_radar_files_round_trip_and_filters(scene):
    out, _ = scene
    for stem in ("000000", "000001"):
        sweeps = [
            read_radar_pcd(out / f"radar/{stem}_sweep{k}.pcd", filters=None) for k in range(5)
        ]
        merged = read_radar_pcd(out / f"radar/{stem}.pcd", filters=None)
        assert merged.shape == (sum(len(s) for s in sweeps), 18)
        assert np.array_equal(merged, np.concatenate(sweeps))
        for s in sweeps:
            real = s[:, F["pdh0"]] == 1
            assert 30 <= real.sum() <= 60
            assert 2 <= (~real).sum() <= 6
            assert np.all(s[:, F["z"]] == 0)
            az = np.degrees(np.arctan2(s[:, F["y"]], s[:, F["x"]]))
            assert np.all(np.abs(az) < 65)
            assert np.array_equal(np.sort(s[:, F["id"]]), np.arange(len(s)))
            # Real returns survive the devkit's default filters.
            assert np.all(s[real, F["invalid_state"]] == 0)
            assert np.all(s[real, F["ambig_state"]] == 3)
            assert np.all(s[real, F["dyn_prop"]] == 1)
        filtered = read_radar_pcd(out / f"radar/{stem}.pcd")
        assert np.array_equal(filtered, merged[RadarFilter().mask(_as_records(merged))])
        assert len(filtered) < len(merged)  # some clutter is flagged invalid


def _as_records(points: np.ndarray) -> np.ndarray:
    rec = np.zeros(len(points), dtype=[(n, "f8") for n in RADAR_FIELDS])
    for i, n in enumerate(RADAR_FIELDS):
        rec[n] = points[:, i]
    return rec


def test_radar_returns_lie_on_surfaces(scene):
    out, _ = scene
    meta = _scene_json(out)
    boxes = [b for b in meta["street"]["boxes"] if b["kind"] != "sidewalk"]
    lo = np.array([b["lo"] for b in boxes])
    hi = np.array([b["hi"] for b in boxes])
    T_cam_from_velo = read_kitti_object_calib(out / "calib/000000.txt").T_cam_from_sensor
    radar_cal = read_json_calib(out / "calib_radar/000000.json")
    T_velo_from_radar = np.linalg.inv(T_cam_from_velo) @ radar_cal.T_cam_from_sensor
    rig = meta["rig"]["radar"]
    for frame, stem in enumerate(("000000", "000001")):
        pts = read_radar_pcd(out / f"radar/{stem}.pcd")
        real = pts[pts[:, F["pdh0"]] == 1]
        T_world = np.array(meta["poses"]["T_world_from_velo"][frame]) @ T_velo_from_radar
        world = np.c_[real[:, :3], np.ones(len(real))] @ T_world.T
        assert np.allclose(world[:, 2], 0.5)  # the radar fan is 0.5 m above the ground
        dist = _box_distance(world[:, :3], lo, hi)
        r = np.hypot(real[:, 0], real[:, 1])
        tol = 3 * rig["range_noise_sigma_m"] + 3 * np.radians(rig["azimuth_noise_sigma_deg"]) * r
        assert np.mean(dist <= tol) > 0.97


# -- underwater --------------------------------------------------------------------------------
def test_underwater_matches_its_truth(scene):
    out, _ = scene
    uw = out / "underwater"
    truth = json.loads((uw / "truth.json").read_text())
    w, h = truth["size"]
    assert (w, h) == (64, 48) and truth["frames"] == 12 and truth["water_frames"] == 8
    albedo = read_image(uw / "albedo.png").astype(np.float64) / 255.0
    assert albedo.shape == (h, w + truth["drift_px_per_frame"] * 11, 3)
    A = np.array(truth["A"])
    B = backscatter(h, w, base=truth["B"]["base"], gradient=truth["B"]["vertical_gradient"])
    assert A[0] < A[1] and A[0] < A[2]  # red is attenuated most
    assert B[..., 2].mean() > B[..., 0].mean()  # blue-green backscatter
    for rec in truth["seafloor"]:
        img = read_image(uw / f"seafloor/{rec['index']:06d}.png").astype(np.float64)
        cone = light_cone(h, w, **rec["cone"])
        col = rec["albedo_offset"][1]
        model = (A * albedo[:, col : col + w] * cone[:, :, None] + B) * 255.0
        unclipped = (model > 5) & (model < 250)
        resid = img[unclipped] - model[unclipped]
        assert abs(resid.mean()) < 0.3
        assert np.abs(resid).mean() < 2.0
    water = np.stack([read_image(uw / f"water/{i:06d}.png") for i in range(8)]).astype(float)
    assert np.abs(np.median(water, axis=0) - B * 255.0).mean() < 1.0
    # The bright spot moves across the frames.
    centres = np.array([rec["cone"]["centre"][0] for rec in truth["seafloor"]])
    assert np.all(np.diff(centres) > 0)


def test_underwater_in_memory_clean_frame():
    seq = generate_underwater(seed=1, frames=5, water_frames=2, size=(40, 30), noise_sigma=0.0)
    assert seq.seafloor.shape == (5, 30, 40, 3) and seq.water.shape == (2, 30, 40, 3)
    for t in range(5):
        expect = np.clip(np.rint(seq.clean_frame(t) * 255.0), 0, 255)
        assert np.array_equal(seq.seafloor[t], expect.astype(np.uint8))
    with pytest.raises(ParameterError):
        generate_underwater(frames=0)


# -- ray casting -------------------------------------------------------------------------------
def test_cast_rays_nearest_hit_faces_and_range():
    boxes = BoxSet.from_corners(
        np.array([[5.0, -1, 0], [10.0, -1, 0]]), np.array([[6.0, 1, 2], [11.0, 1, 2]]), group_size=1
    )
    origin = np.array([0.0, 0.0, 1.0])
    d = np.array(
        [
            [1.0, 0, 0],  # hits box 0 front face at t = 5, normal -x
            [-1.0, 0, 0],  # nothing behind
            [1.0, 0, -0.5],  # ground at t = 2 before any box
            [0.0, 0, 1.0],  # straight up: sky
            [2.0, 0, 0],  # unnormalised: t in units of |d| -> 2.5
        ]
    )
    hits = cast_rays(origin, d, boxes)
    assert np.allclose(hits.t[[0, 2, 4]], [5.0, 2.0, 2.5])
    assert list(hits.index) == [0, -1, -2, -1, 0]
    assert np.array_equal(hits.normals[0], [-1, 0, 0]) and np.array_equal(
        hits.normals[2], [0, 0, 1]
    )
    assert np.allclose(hits.points[0], [5, 0, 1]) and np.isnan(hits.points[1]).all()
    assert np.allclose(hits.uv[0], [0, 1])  # a face normal to x is textured by (y, z)
    assert cast_rays(origin, d[:1], boxes, t_max=4.0).index[0] == -1
    # From inside a box the far wall is not an entry face: the next box is hit instead.
    inside = cast_rays(np.array([5.5, 0, 1.0]), d[:1], boxes, ground_z=None)
    assert inside.index[0] == 1 and inside.t[0] == pytest.approx(4.5)
    empty = BoxSet.from_corners(np.zeros((0, 3)), np.zeros((0, 3)))
    assert cast_rays(origin, d, empty).index.tolist() == [-1, -1, -2, -1, -1]
    with pytest.raises(ParameterError):
        cast_rays(origin, d[:, :2], boxes)


def test_sample_data_regenerates_byte_for_byte(tmp_path):
    """sample_data/synthetic is exactly what the default (single-street) mode makes from its
    scene.json: the video mode must leave that output unchanged."""
    from sparsetools.synth.verify import regenerate_and_compare

    ref = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"
    result = regenerate_and_compare(ref, tmp_path / "again")
    assert result["files"] > 80
    assert result["missing"] == [] and result["different"] == [] and result["extra"] == []
    assert result["identical"] == result["files"]
