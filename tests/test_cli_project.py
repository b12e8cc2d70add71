"""``sparsetools project``: layouts, formats, resume, nuScenes multi-sweep, bad input."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from sparsetools.cli.main import cli
from sparsetools.io.image import read_depth_png

W, H = 320, 96


# -- helpers ------------------------------------------------------------------------------------


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def error_lines(result):
    """stderr lines other than log warnings: the error message, which must be one line."""
    return [ln for ln in result.stderr.splitlines() if ln.strip() and not ln.startswith("WARNING:")]


def assert_clean_failure(result, code, match):
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    if code == 1:
        lines = error_lines(result)
        assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
        assert match in lines[0], lines[0]
    else:
        assert match in result.stderr, result.stderr


def files_under(folder: Path) -> list[str]:
    if not folder.exists():
        return []
    return sorted(
        str(p.relative_to(folder))
        for p in folder.rglob("*")
        if p.is_file() and ".sparsetools" not in p.parts
    )


def digest(folder: Path) -> dict[str, str]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


def reference_depth(cam_points, K, width, height, min_depth=0.1, offset=0):
    """Camera-frame points -> nearest depth per pixel (independent numpy reference)."""
    p = np.asarray(cam_points, dtype=np.float64)[:, :3]
    uvw = p @ K.T
    z = uvw[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.round(uvw[:, 0] / z) + offset
        v = np.round(uvw[:, 1] / z) + offset
        keep = (z > min_depth) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    buf = np.full(width * height, np.inf)
    np.minimum.at(buf, v[keep].astype(np.int64) * width + u[keep].astype(np.int64), z[keep])
    return np.where(np.isfinite(buf), buf, 0).astype(np.float32).reshape(height, width)


def png_quantised(depth):
    """What a KITTI depth PNG stores and gives back for ``depth`` (metres)."""
    q = np.clip(np.rint(depth.astype(np.float64) * 256), 0, 65535)
    return (q / 256).astype(np.float32)


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    from sparsetools.synth import generate_scene

    out = tmp_path_factory.mktemp("synth") / "scene"
    generate_scene(out, seed=1, frames=5, width=W, height=H, underwater_frames=0)
    return out


@pytest.fixture(scope="module")
def rig():
    from sparsetools.synth.rig import Rig

    return Rig.kitti(W, H)


def velo_to_cam(points, rig):
    T = rig.T_cam_from_velo
    return points[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]


# -- plain clouds + calibration -----------------------------------------------------------------


def test_folder_of_clouds_with_per_frame_calib(synth, rig, tmp_path):
    out = tmp_path / "out"
    before = digest(synth)
    r = run(
        "project",
        synth / "velodyne",
        "--calib",
        synth / "calib",
        "--image-size",
        f"{W}x{H}",
        "-o",
        out,
        "--json",
    )
    assert r.exit_code == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["frames"] == summary["processed"] == 5 and summary["failed"] == 0
    from sparsetools.io.kitti import read_velodyne_bin

    total_valid = 0
    for i in range(5):
        pts = read_velodyne_bin(synth / "velodyne" / f"{i:06d}.bin")
        ref = reference_depth(velo_to_cam(pts, rig), rig.K, W, H)
        got = read_depth_png(out / f"{i:06d}.png")
        np.testing.assert_array_equal(got, png_quantised(ref))
        total_valid += int(np.count_nonzero(ref))
        cal = json.loads((out / "calib" / f"{i:06d}.json").read_text())
        assert (cal["width"], cal["height"]) == (W, H) and cal["frame"] == f"{i:06d}"
    assert summary["valid_pixels"] == total_valid
    assert summary["density_pct"] == pytest.approx(100 * total_valid / (5 * W * H), abs=1e-3)
    assert summary["points_in"] > summary["points_in_image"] >= total_valid
    assert digest(synth) == before  # inputs untouched


def test_synthetic_lidar_agrees_with_dense_ground_truth(synth):
    """Projected LiDAR vs the renderer's depth, at each winning point's exact sub-pixel spot."""
    from scipy.ndimage import map_coordinates

    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.projection import project_points_with_index, project_uvz

    calib = load_calibration(synth / "calib" / "000002.txt", image_size=(W, H))
    pts = read_velodyne_bin(synth / "velodyne" / "000002.bin")
    gt = read_depth_png(synth / "depth_gt" / "000002.png")
    _, index = project_points_with_index(pts, calib)
    u, v, z = project_uvz(pts, calib.projection)
    i = index[index >= 0]
    inv = np.where(gt > 0, 1.0 / np.maximum(gt, 1e-6), 0.0)  # depth is linear in 1/z on planes
    inside = map_coordinates((gt > 0).astype(float), [v[i], u[i]], order=1) > 0.999
    with np.errstate(divide="ignore"):
        truth = 1.0 / map_coordinates(inv, [v[i], u[i]], order=1)
    err = np.abs(z[i] - truth)[inside]
    sigma = 0.015  # Rig.lidar_range_noise
    assert inside.mean() > 0.95
    assert np.median(err) < 1.5 * sigma
    assert np.mean(err < 3 * sigma) > 0.85  # the rest: occlusion edges (LiDAR/camera parallax)


def test_kitti_raw_layout_on_synthetic_rig(synth, rig, tmp_path):
    date = tmp_path / "2011_09_26"
    drive = date / "2011_09_26_drive_0001_sync" / "velodyne_points" / "data"
    drive.mkdir(parents=True)
    shutil.copy(synth / "velodyne" / "000003.bin", drive / "0000000003.bin")

    def fmt(a):
        return " ".join(f"{x:.12e}" for x in np.ravel(a))

    (date / "calib_cam_to_cam.txt").write_text(
        f"calib_time: 09-Jan-2012 13:57:47\nR_rect_00: {fmt(np.eye(3))}\n"
        f"P_rect_02: {fmt(rig.P)}\nS_rect_02: {W} {H}\n"
    )
    T = rig.T_cam_from_velo
    (date / "calib_velo_to_cam.txt").write_text(f"R: {fmt(T[:3, :3])}\nT: {fmt(T[:3, 3])}\n")
    out = tmp_path / "out"
    r = run("project", "--kitti-raw", drive.parent.parent, "-o", out, "--format", "npy")
    assert r.exit_code == 0, r.stderr
    from sparsetools.io.kitti import read_velodyne_bin

    pts = read_velodyne_bin(drive / "0000000003.bin")
    np.testing.assert_array_equal(
        np.load(out / "2011_09_26_drive_0001_sync" / "0000000003.npy"),
        reference_depth(velo_to_cam(pts, rig), rig.K, W, H),
    )


def test_resize_and_crop_adjust_intrinsics_consistently(synth, tmp_path):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin

    out = tmp_path / "out"
    r = run(
        "project",
        synth / "velodyne" / "000001.bin",
        "--calib",
        synth / "calib" / "000001.txt",
        "--image",
        synth / "image_2" / "000001.png",
        "--resize",
        "0.5",
        "--crop",
        "8,10,30,140",
        "--format",
        "npy",
        "-o",
        out,
    )
    assert r.exit_code == 0, r.stderr
    depth = np.load(out / "000001.npy")
    assert depth.shape == (30, 140) and depth.dtype == np.float32
    base = load_calibration(synth / "calib" / "000001.txt", image_size=(W, H))
    expected = base.resized(0.5).cropped(8, 10, 30, 140)
    written = load_calibration(out / "calib" / "000001.json")
    np.testing.assert_allclose(written.K, expected.K, atol=1e-12)
    np.testing.assert_allclose(written.projection, expected.projection, atol=1e-12)
    assert written.size == (140, 30)
    # By the METHODS.md rules: f' = f/2, c' = (c + 0.5)/2 - 0.5 - offset.
    assert written.fx == pytest.approx(base.fx / 2)
    assert written.cx == pytest.approx((base.cx + 0.5) / 2 - 0.5 - 10)
    assert written.cy == pytest.approx((base.cy + 0.5) / 2 - 0.5 - 8)
    pts = read_velodyne_bin(synth / "velodyne" / "000001.bin")
    T = expected.T_cam_from_sensor
    cam = pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_array_equal(depth, reference_depth(cam, expected.K, 140, 30))


def test_parquet_rows_equal_npy_maps_and_resume(synth, tmp_path):
    import pyarrow.parquet as pq

    npy, pqo = tmp_path / "npy", tmp_path / "pq"
    velo = synth / "velodyne"
    common = ["--calib", synth / "calib", "--image-size", f"{W}x{H}"]
    assert run("project", velo, *common, "-o", npy, "--format", "npy").exit_code == 0
    # First two frames, then all five: the first two are kept, three are added.
    r = run(
        "project",
        velo / "000000.bin",
        velo / "000001.bin",
        *common,
        "-o",
        pqo,
        "--format",
        "parquet",
    )
    assert r.exit_code == 0, r.stderr
    first = pq.read_table(pqo / "sparse.parquet")
    assert first.column("frame").to_pylist() == ["000000", "000001"]
    # A part without a record (here copied from another run) is not trusted: recomputed.
    r = run(
        "project", velo / "000002.bin", *common, "-o", tmp_path / "scratch", "--format", "parquet"
    )
    parts = pqo / "sparse.parts"
    parts.mkdir()
    shutil.copy(tmp_path / "scratch" / "sparse.parquet", parts / "000002.parquet")
    shutil.copy(tmp_path / "scratch" / "calib" / "000002.json", pqo / "calib" / "000002.json")
    r = run("project", velo, *common, "-o", pqo, "--format", "parquet", "--json")
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["skipped_existing"] == 2 and s["processed"] == 3
    assert not parts.exists() and files_under(pqo) == sorted(
        ["sparse.parquet"] + [f"calib/{i:06d}.json" for i in range(5)]
    )
    table = pq.read_table(pqo / "sparse.parquet")
    assert table.column("frame").to_pylist() == [f"{i:06d}" for i in range(5)]
    assert table.schema.field("u").type.value_type.bit_width == 16
    assert str(table.schema.field("depth").type.value_type) == "float"
    for row in table.to_pylist():
        d = np.zeros((row["height"], row["width"]), np.float32)
        d[np.array(row["v"]), np.array(row["u"])] = np.array(row["depth"], np.float32)
        np.testing.assert_array_equal(d, np.load(npy / f"{row['frame']}.npy"))
    assert table.slice(0, 2).to_pylist() == first.to_pylist()
    # A complete rerun does nothing; --overwrite recomputes everything.
    s = json.loads(run("project", velo, *common, "-o", pqo, "--format", "parquet", "--json").stdout)
    assert s["skipped_existing"] == 5 and s["processed"] == 0
    s = json.loads(
        run(
            "project", velo, *common, "-o", pqo, "--format", "parquet", "--json", "--overwrite"
        ).stdout
    )
    assert s["processed"] == 5
    assert pq.read_table(pqo / "sparse.parquet").to_pylist() == table.to_pylist()


def test_two_workers_write_the_same_bytes(synth, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    args = ["project", synth / "velodyne", "--calib", synth / "calib", "--image-size", f"{W}x{H}"]
    assert run(*args, "-o", a, "--workers", "1").exit_code == 0
    r = run(*args, "-o", b, "--workers", "2", "--json")
    assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["processed"] == 5
    for name in files_under(a):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


# -- real KITTI ---------------------------------------------------------------------------------


@pytest.mark.real
def test_kitti_object_layout_real_frames(kitti_object, tmp_path):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin

    out = tmp_path / "out"
    r = run("project", "--kitti-object", kitti_object, "-o", out, "--json")
    assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["processed"] == 3
    for stem, size in (("000000", (1224, 370)), ("000001", (1242, 375))):
        calib = load_calibration(kitti_object / "calib" / f"{stem}.txt", image_size=size)
        pts = read_velodyne_bin(kitti_object / "velodyne" / f"{stem}.bin")
        T = calib.T_cam_from_sensor
        # P2 carries a translation column: fold it into the camera-frame points.
        P = calib.P
        cam = pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        cam = cam + np.linalg.solve(P[:, :3], P[:, 3])
        got = read_depth_png(out / f"{stem}.png")
        assert got.shape == (size[1], size[0])
        ref = reference_depth(cam, P[:, :3], *size)
        # Same pixels; values equal after PNG quantisation (the fold changes the last ulp).
        np.testing.assert_array_equal(got > 0, ref > 0)
        np.testing.assert_allclose(got, png_quantised(ref), atol=1 / 256 + 1e-6)


@pytest.mark.real
def test_kitti_raw_date_folder_equals_object_calib(real_dir, kitti_object, tmp_path):
    date = tmp_path / "2011_09_26"
    data = date / "2011_09_26_drive_0005_sync" / "velodyne_points" / "data"
    data.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(real_dir / "kitti-raw-calib-2011_09_26" / name, date / name)
    shutil.copy(kitti_object / "velodyne" / "000001.bin", data / "000001.bin")
    a, b = tmp_path / "raw", tmp_path / "obj"
    assert run("project", "--kitti-raw", data.parent.parent, "-o", a).exit_code == 0
    r = run(
        "project",
        kitti_object / "velodyne" / "000001.bin",
        "--calib",
        kitti_object / "calib" / "000001.txt",
        "--image",
        kitti_object / "image_2" / "000001.png",
        "-o",
        b,
    )
    assert r.exit_code == 0, r.stderr
    assert (a / "2011_09_26_drive_0005_sync" / "000001.png").read_bytes() == (
        b / "000001.png"
    ).read_bytes()


@pytest.mark.real
def test_nuscenes_json_calibration_real_lidar(nuscenes_demo, tmp_path):
    cloud = next(nuscenes_demo.glob("*LIDAR_TOP*.pcd.bin"))
    out = tmp_path / "out"
    r = run(
        "project",
        cloud,
        "--calib",
        nuscenes_demo / "calib_derived_from_pkl.json",
        "--camera",
        "CAM_FRONT",
        "--min-depth",
        "1",
        "-o",
        out,
        "--format",
        "npy",
        "--json",
    )
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    stem = cloud.name[: -len(".pcd.bin")]
    depth = np.load(out / f"{stem}.npy")
    assert depth.shape == (900, 1600)
    # All points in the image with depth > 1 m (no margin): a little above the devkit's 3053.
    assert 3053 <= s["points_in_image"] < 3200
    assert 0 < s["valid_pixels"] <= s["points_in_image"]


# -- nuScenes tree with a moving ego -----------------------------------------------------------


def _quat_wxyz(R):
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return [float(w), float(x), float(y), float(z)]


def build_nuscenes_tree(root: Path, synth: Path, rig, *, camera_shift=0.0, with_size=True):
    """v1.0-mini tables over synthetic frames 0..4: radar sweeps 0..4 (key frames 2 and 4),
    camera and LIDAR_TOP key frames at 2 and 4. The ego drives 1 m per frame (synthetic
    world); "global" is that world under a rotation and offset so the chain cannot cancel
    trivially. The camera may be captured ``camera_shift`` metres further along."""
    from sparsetools.io.nuscenes import read_radar_pcd, write_radar_pcd
    from sparsetools.io.pointcloud import read_points

    scene = json.loads((synth / "scene.json").read_text())
    origins = [np.array(T)[:3, 3] for T in scene["poses"]["T_world_from_velo"]]
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("zyx", [37, 2, -1], degrees=True).as_matrix()
    G[:3, 3] = [411.3, 1180.9, 0.2]

    def ego_pose(tok, origin):
        T = np.eye(4)
        T[:3, 3] = origin
        T = G @ T
        return {
            "token": tok,
            "rotation": _quat_wxyz(T[:3, :3]),
            "translation": T[:3, 3].tolist(),
            "timestamp": 0,
        }

    version = root / "v1.0-mini"
    version.mkdir(parents=True)
    sensors = [
        {"token": "s-radar", "channel": "RADAR_FRONT", "modality": "radar"},
        {"token": "s-cam", "channel": "CAM_FRONT", "modality": "camera"},
        {"token": "s-lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
    ]
    T_ego_from_cam = np.linalg.inv(rig.T_cam_from_velo)
    calibrated = [
        {
            "token": "cs-radar",
            "sensor_token": "s-radar",
            "rotation": [1, 0, 0, 0],
            "translation": rig.T_velo_from_radar[:3, 3].tolist(),
            "camera_intrinsic": [],
        },
        {
            "token": "cs-cam",
            "sensor_token": "s-cam",
            "rotation": _quat_wxyz(T_ego_from_cam[:3, :3]),
            "translation": T_ego_from_cam[:3, 3].tolist(),
            "camera_intrinsic": rig.K.tolist(),
        },
        {
            "token": "cs-lidar",
            "sensor_token": "s-lidar",
            "rotation": [1, 0, 0, 0],
            "translation": [0, 0, 0],
            "camera_intrinsic": [],
        },
    ]
    keys = (2, 4)
    samples, sample_data, poses = [], [], []
    for k in keys:
        samples.append({"token": f"sample-{k}", "timestamp": 1000 * k, "scene_token": "scene"})
    for i in range(5):
        owner = next(k for k in keys if k >= i)
        rel = f"{'samples' if i in keys else 'sweeps'}/RADAR_FRONT/radar_{i}.pcd"
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        # All returns of the synthetic sweep (the default filters drop the clutter).
        write_radar_pcd(
            root / rel, read_radar_pcd(synth / "radar" / f"{i:06d}_sweep0.pcd", filters=None)
        )
        poses.append(ego_pose(f"ep-radar-{i}", origins[i]))
        sample_data.append(
            {
                "token": f"sd-radar-{i}",
                "sample_token": f"sample-{owner}",
                "ego_pose_token": f"ep-radar-{i}",
                "calibrated_sensor_token": "cs-radar",
                "filename": rel,
                "is_key_frame": i in keys,
                "timestamp": 1000 * i,
                "prev": f"sd-radar-{i - 1}" if i else "",
                "next": f"sd-radar-{i + 1}" if i < 4 else "",
                "width": 0,
                "height": 0,
            }
        )
    for k in keys:
        cam_rel = f"samples/CAM_FRONT/cam_{k}.png"
        (root / cam_rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(synth / "image_2" / f"{k:06d}.png", root / cam_rel)
        poses.append(ego_pose(f"ep-cam-{k}", origins[k] + [camera_shift, 0, 0]))
        sample_data.append(
            {
                "token": f"sd-cam-{k}",
                "sample_token": f"sample-{k}",
                "ego_pose_token": f"ep-cam-{k}",
                "calibrated_sensor_token": "cs-cam",
                "filename": cam_rel,
                "is_key_frame": True,
                "timestamp": 1000 * k,
                "prev": "",
                "next": "",
                "width": W if with_size else 0,
                "height": H if with_size else 0,
            }
        )
        lidar_rel = f"samples/LIDAR_TOP/lidar_{k}.pcd.bin"
        (root / lidar_rel).parent.mkdir(parents=True, exist_ok=True)
        pts = read_points(synth / "velodyne" / f"{k:06d}.bin")
        ring = np.load(synth / "velodyne_ring" / f"{k:06d}.npy").astype(np.float32)
        np.column_stack([pts, ring]).astype("<f4").tofile(root / lidar_rel)
        poses.append(ego_pose(f"ep-lidar-{k}", origins[k]))
        sample_data.append(
            {
                "token": f"sd-lidar-{k}",
                "sample_token": f"sample-{k}",
                "ego_pose_token": f"ep-lidar-{k}",
                "calibrated_sensor_token": "cs-lidar",
                "filename": lidar_rel,
                "is_key_frame": True,
                "timestamp": 1000 * k,
                "prev": "",
                "next": "",
                "width": 0,
                "height": 0,
            }
        )
    for name, rows in (
        ("sample", samples),
        ("sample_data", sample_data),
        ("ego_pose", poses),
        ("calibrated_sensor", calibrated),
        ("sensor", sensors),
    ):
        (version / f"{name}.json").write_text(json.dumps(rows))
    return origins


def expected_radar_map(synth, rig, origins, key, n_sweeps, camera_shift):
    """Radar sweeps of frames key, key-1, ... mapped to the key camera through the world."""
    from sparsetools.io.nuscenes import read_radar_pcd

    cam_points = []
    for i in range(key, max(key - n_sweeps, -1), -1):
        pts = read_radar_pcd(synth / "radar" / f"{i:06d}_sweep0.pcd")  # devkit filters
        world = pts[:, :3].astype(np.float64) + rig.T_velo_from_radar[:3, 3] + origins[i]
        velo_at_camera = world - (origins[key] + [camera_shift, 0, 0])
        cam_points.append(velo_to_cam(velo_at_camera, rig))
    return reference_depth(np.vstack(cam_points), rig.K, W, H)


@pytest.mark.parametrize("camera_shift", [0.0, 0.7])
def test_nuscenes_multisweep_radar_matches_independent_transform(
    synth, rig, tmp_path, camera_shift
):
    root = tmp_path / "nuscenes"
    origins = build_nuscenes_tree(
        root, synth, rig, camera_shift=camera_shift, with_size=camera_shift == 0
    )
    before = digest(root)
    out = tmp_path / "out"
    r = run(
        "project",
        "--nuscenes",
        root,
        "--nuscenes-version",
        "v1.0-mini",
        "--sensor",
        "RADAR_FRONT",
        "--camera",
        "CAM_FRONT",
        "--sweeps",
        "5",
        "-o",
        out,
        "--format",
        "npy",
        "--json",
    )
    assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["processed"] == 2
    for key, n_avail in ((2, 3), (4, 5)):
        got = np.load(out / "scene" / f"sample-{key}.npy")
        ref = expected_radar_map(synth, rig, origins, key, 5, camera_shift)
        assert np.count_nonzero(ref) > 60 * n_avail * 0.3
        np.testing.assert_array_equal(got > 0, ref > 0)
        np.testing.assert_allclose(got, ref, rtol=1e-5)
        # More sweeps, more points: one sweep gives a strict subset of the pixels.
    r = run(
        "project", "--nuscenes", root, "--sweeps", "1", "-o", tmp_path / "one", "--format", "npy"
    )
    assert r.exit_code == 0, r.stderr
    one = np.load(tmp_path / "one" / "scene" / "sample-4.npy")
    np.testing.assert_allclose(
        one, expected_radar_map(synth, rig, origins, 4, 1, camera_shift), rtol=1e-5
    )
    assert np.count_nonzero(one) < np.count_nonzero(np.load(out / "scene" / "sample-4.npy"))
    cal = json.loads((out / "calib" / "scene" / "sample-4.json").read_text())
    assert cal["cloud"][0].endswith("radar_4.pcd") and len(cal["cloud"]) == 5
    assert digest(root) == before


def test_nuscenes_radar_agrees_with_ground_truth_and_lidar_top(synth, rig, tmp_path):
    root = tmp_path / "nuscenes"
    build_nuscenes_tree(root, synth, rig)
    out = tmp_path / "radar"
    assert run("project", "--nuscenes", root, "-o", out, "--format", "npy").exit_code == 0
    gt = read_depth_png(synth / "depth_gt" / "000004.png")
    radar = np.load(out / "scene" / "sample-4.npy")
    m = (radar > 0) & (gt > 0)
    assert m.sum() > 100
    # Static world: accumulated sweeps land on the rendered surfaces within the radar noise
    # (0.2 m range, 1 deg azimuth).
    assert np.median(np.abs(radar[m] - gt[m])) < 0.5
    lidar_out = tmp_path / "lidar"
    r = run(
        "project", "--nuscenes", root, "--sensor", "LIDAR_TOP", "-o", lidar_out, "--format", "npy"
    )
    assert r.exit_code == 0, r.stderr
    from sparsetools.io.kitti import read_velodyne_bin

    pts = read_velodyne_bin(synth / "velodyne" / "000004.bin")
    ref = reference_depth(velo_to_cam(pts, rig), rig.K, W, H)
    got = np.load(lidar_out / "scene" / "sample-4.npy")
    np.testing.assert_array_equal(got > 0, ref > 0)
    np.testing.assert_allclose(got, ref, rtol=1e-5)


# -- bad input ----------------------------------------------------------------------------------


@pytest.fixture()
def frame(synth, tmp_path):
    """One synthetic frame copied to its own folder (cloud + calib + image)."""
    d = tmp_path / "in"
    for sub, name in (
        ("velodyne", "000000.bin"),
        ("calib", "000000.txt"),
        ("image_2", "000000.png"),
    ):
        (d / sub).mkdir(parents=True)
        shutil.copy(synth / sub / name, d / sub / name)
    return d


def project_frame_args(d, out, *extra):
    return (
        "project",
        d / "velodyne",
        "--calib",
        d / "calib",
        "--image",
        d / "image_2",
        "-o",
        out,
        *extra,
    )


def test_empty_cloud_writes_an_empty_map_and_says_so(frame, tmp_path):
    (frame / "velodyne" / "000000.bin").write_bytes(b"")
    out = tmp_path / "out"
    r = run(*project_frame_args(frame, out, "--json"))
    assert r.exit_code == 0, r.stderr
    assert json.loads(r.stdout)["empty_maps"] == 1
    assert "empty depth map" in r.stderr and "no points" in r.stderr
    assert not read_depth_png(out / "000000.png").any()
    assert read_depth_png(out / "000000.png").shape == (H, W)


def test_all_points_behind_the_camera(frame, tmp_path):
    pts = np.fromfile(frame / "velodyne" / "000000.bin", dtype="<f4").reshape(-1, 4)
    behind = pts[pts[:, 0] < -1]
    behind.astype("<f4").tofile(frame / "velodyne" / "000000.bin")
    out = tmp_path / "out"
    r = run(*project_frame_args(frame, out, "--json"))
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["empty_maps"] == 1 and s["points_in"] == len(behind) > 1000
    assert s["points_in_image"] == 0
    assert "in front of the camera" in r.stderr
    assert not read_depth_png(out / "000000.png").any()


def test_nan_and_inf_points_are_dropped_with_a_warning(frame, rig, tmp_path):
    path = frame / "velodyne" / "000000.bin"
    pts = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    bad = pts.copy()
    bad[5, 0] = np.nan
    bad[9, 2] = np.inf
    bad[11, 3] = -np.inf
    bad.tofile(path)
    out = tmp_path / "out"
    r = run(*project_frame_args(out=out, d=frame))
    assert r.exit_code == 0, r.stderr
    assert "dropped 3 point(s) with NaN/Inf" in r.stderr
    good = np.delete(pts, [5, 9, 11], axis=0)
    ref = reference_depth(velo_to_cam(good, rig), rig.K, W, H)
    np.testing.assert_array_equal(read_depth_png(out / "000000.png"), png_quantised(ref))


def test_truncated_bin_fails_cleanly(frame, tmp_path):
    path = frame / "velodyne" / "000000.bin"
    path.write_bytes(path.read_bytes()[:-3])
    before = digest(frame)
    out = tmp_path / "out"
    r = run(*project_frame_args(frame, out))
    assert_clean_failure(r, 1, "not a multiple of 16")
    assert files_under(out) == []
    assert digest(frame) == before


def test_on_error_skip_keeps_the_good_frames(frame, synth, tmp_path):
    shutil.copy(synth / "velodyne" / "000001.bin", frame / "velodyne" / "000001.bin")
    shutil.copy(synth / "calib" / "000001.txt", frame / "calib" / "000001.txt")
    shutil.copy(synth / "image_2" / "000001.png", frame / "image_2" / "000001.png")
    (frame / "velodyne" / "000000.bin").write_bytes(b"\0" * 17)
    out = tmp_path / "out"
    r = run(*project_frame_args(frame, out, "--on-error", "skip"))
    assert r.exit_code == 1
    assert "failed 000000" in r.stdout and "Traceback" not in r.stderr
    assert files_under(out) == ["000001.png", "calib/000001.json"]


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: "\n".join(ln for ln in t.splitlines() if not ln.startswith("P2:")), "'P2'"),
        (
            lambda t: "\n".join(
                "P2: " + " ".join(["0"] * 12) if ln.startswith("P2:") else ln
                for ln in t.splitlines()
            ),
            "singular",
        ),
        (lambda t: t.replace("R0_rect: 1.0", "R0_rect: abc"), "non-numeric"),
    ],
)
def test_bad_calibration_fails_before_writing(frame, tmp_path, edit, message):
    calib = frame / "calib" / "000000.txt"
    calib.write_text(edit(calib.read_text()))
    before = digest(frame)
    out = tmp_path / "out"
    r = run(
        "project",
        frame / "velodyne" / "000000.bin",
        "--calib",
        calib,
        "--image-size",
        f"{W}x{H}",
        "-o",
        out,
    )
    assert_clean_failure(r, 1, message)
    assert files_under(out) == []
    assert digest(frame) == before


def test_image_size_missing(frame, tmp_path):
    out = tmp_path / "out"
    r = run("project", frame / "velodyne", "--calib", frame / "calib", "-o", out)
    assert_clean_failure(r, 1, "image size missing")
    assert files_under(out) == []


def test_output_is_a_file(frame, tmp_path):
    out = tmp_path / "out"
    out.write_text("not a folder")
    r = run(*project_frame_args(frame, out))
    assert_clean_failure(r, 1, "is a file")
    assert out.read_text() == "not a folder"


def test_output_not_writable(frame, tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    real_access = os.access
    # Tests may run as root, for whom chmod does not bite: deny write access the way a
    # read-only mount would, through os.access.
    monkeypatch.setattr(
        os,
        "access",
        lambda p, mode, **kw: (
            False
            if (Path(p).resolve() == out.resolve() and mode & os.W_OK)
            else real_access(p, mode, **kw)
        ),
    )
    r = run(*project_frame_args(frame, out))
    assert_clean_failure(r, 1, "not writable")
    assert files_under(out) == []


def test_output_inside_input_folder(frame):
    before = digest(frame)
    r = run(*project_frame_args(frame, frame / "velodyne" / "depth"))
    assert_clean_failure(r, 1, "inside the input folder")
    assert digest(frame) == before and not (frame / "velodyne" / "depth").exists()


def test_output_would_replace_an_input(frame, tmp_path):
    pts = np.fromfile(frame / "velodyne" / "000000.bin", dtype="<f4").reshape(-1, 4)
    np.save(tmp_path / "000000.npy", pts)
    before = (tmp_path / "000000.npy").read_bytes()
    r = run(
        "project",
        tmp_path / "000000.npy",
        "--calib",
        frame / "calib" / "000000.txt",
        "--image-size",
        f"{W}x{H}",
        "--format",
        "npy",
        "-o",
        tmp_path,
    )
    assert_clean_failure(r, 1, "would replace an input")
    assert (tmp_path / "000000.npy").read_bytes() == before


def test_crop_outside_the_image(frame, tmp_path):
    r = run(*project_frame_args(frame, tmp_path / "out", "--crop", "0,0,200,200"))
    assert_clean_failure(r, 1, "does not fit")
    assert files_under(tmp_path / "out") == []


@pytest.mark.parametrize(
    "args, message",
    [
        ([], "exactly one source"),
        (["{d}/velodyne", "--kitti-object", "{d}"], "exactly one source"),
        (["--calib", "{d}/calib"], "exactly one source"),
        (["{d}/velodyne"], "give --calib"),
        (["{d}/velodyne", "--calib", "{d}/calib", "--crop", "1,2,3"], "WxH+LEFT+TOP"),
        (["{d}/velodyne", "--calib", "{d}/calib", "--crop", "5x0+0+0"], "W, H > 0"),
        (["{d}/velodyne", "--calib", "{d}/calib", "--pixel-offset", "1"], "--pixel-offset"),
        (["--kitti-object", "{d}", "--camera", "left"], "camera"),
        (["{d}/velodyne", "--calib", "{d}/calib", "--resize", "0"], "finite number > 0"),
        (["{d}/nothing", "--calib", "{d}/calib"], "does not exist"),
    ],
)
def test_usage_errors(frame, tmp_path, args, message):
    out = tmp_path / "out"
    r = run("project", *[a.format(d=frame) for a in args], "-o", out)
    assert_clean_failure(r, 2, message)
    assert not out.exists()


def test_depth_beyond_png_range_is_counted_as_clipped(frame, tmp_path):
    # Velodyne x forward, y left: camera depth = x - 0.27 m; the far point 30 m to the left.
    pts = np.array([[300.0, 30.0, -0.08, 0.5], [20.0, 0, -0.08, 0.5]], dtype="<f4")
    pts.tofile(frame / "velodyne" / "000000.bin")
    out = tmp_path / "out"
    r = run(*project_frame_args(frame, out, "--json"))
    assert r.exit_code == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["clipped"] == 1 and s["valid_pixels"] == 2
    png = read_depth_png(out / "000000.png")
    assert sorted(png[png > 0].tolist()) == [pytest.approx(19.73, abs=1 / 256), 65535 / 256]
    assert "clipped" in r.stderr
    # npy keeps the exact value.
    r = run(*project_frame_args(frame, tmp_path / "npy", "--format", "npy"))
    assert np.load(tmp_path / "npy" / "000000.npy").max() == pytest.approx(299.73, abs=1e-3)


def test_foreign_sparse_parquet_is_refused(frame, tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    out = tmp_path / "out"
    out.mkdir()
    pq.write_table(pa.table({"x": [1, 2]}), out / "sparse.parquet")
    before = (out / "sparse.parquet").read_bytes()
    r = run(*project_frame_args(frame, out, "--format", "parquet"))
    assert_clean_failure(r, 1, "sparse.parquet")
    assert (out / "sparse.parquet").read_bytes() == before
    assert files_under(out) == ["sparse.parquet"]


# -- --filter-occluded ----------------------------------------------------------------------------


@pytest.mark.real
def test_filter_occluded_removes_what_the_kernel_removes_and_is_recorded(real_dir, tmp_path):
    from sparsetools.io.calib import load_calibration
    from sparsetools.ops.occlusion import filter_occluded

    drive = real_dir / "kitti-raw-sequence-2011_09_26"
    scan = drive / "velodyne_points" / "data" / "0000000000.bin"
    args = (scan, "--calib", drive, "--image-size", "1242x375", "--format", "npy")
    plain, filt = tmp_path / "plain", tmp_path / "filt"
    assert run("project", *args, "-o", plain).exit_code == 0
    r = run("project", *args, "-o", filt, "--filter-occluded", "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.output)
    a = np.load(plain / "0000000000.npy")
    b = np.load(filt / "0000000000.npy")
    fx = load_calibration(drive, camera=2).fx
    expected, removed = filter_occluded(a, fx=fx)
    np.testing.assert_array_equal(b, expected)
    # A few per cent of a real scan are see-through points; the rest is kept untouched.
    assert 0 < removed.sum() < 0.1 * (a > 0).sum()
    assert summary["occluded_pixels"] == int(removed.sum())
    # The option is part of the folder's record: a rerun without it is refused, naming it.
    again = run("project", *args, "-o", filt)
    assert again.exit_code != 0 and "--filter-occluded" in again.output
