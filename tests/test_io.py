"""Readers and writers: round trips and every bad input named in the foundation issue."""

from __future__ import annotations

import json
import os
import struct
import zlib

import cv2
import numpy as np
import pytest

import sparsetools as st
from sparsetools.errors import FormatError, OutputError
from sparsetools.io.atomic import (
    TMP_PREFIX,
    atomic_path,
    atomic_write_bytes,
    remove_stale_temporaries,
)
from sparsetools.io.image import image_header_size
from sparsetools.io.kitti import read_velodyne_bin, write_velodyne_bin
from sparsetools.io.nuscenes import (
    RADAR_FIELDS,
    NuScenesTables,
    RadarFilter,
    quaternion_to_matrix,
    read_lidar_pcd_bin,
    read_radar_pcd,
    write_radar_pcd,
)
from sparsetools.io.pointcloud import cloud_kind, read_points, write_points


def _cloud(n=100, c=4, seed=0):
    return np.random.default_rng(seed).normal(size=(n, c)).astype(np.float32)


# -- KITTI .bin ----------------------------------------------------------------------------------
def test_bin_round_trip_is_bit_exact(tmp_path):
    pts = _cloud()
    write_velodyne_bin(tmp_path / "a.bin", pts)
    back = read_velodyne_bin(tmp_path / "a.bin")
    assert back.dtype == np.float32 and back.shape == (100, 4)
    assert back.tobytes() == pts.tobytes()
    assert (tmp_path / "a.bin").stat().st_size == 100 * 16


def test_bin_zero_length_is_an_empty_cloud(tmp_path):
    (tmp_path / "e.bin").write_bytes(b"")
    assert read_points(tmp_path / "e.bin").shape == (0, 4)


@pytest.mark.parametrize("extra", [1, 5, 15])
def test_bin_truncated_is_rejected(tmp_path, extra):
    (tmp_path / "t.bin").write_bytes(_cloud(3).tobytes() + b"\0" * extra)
    with pytest.raises(FormatError, match="not a multiple of 16"):
        read_points(tmp_path / "t.bin")


def test_bin_non_finite_rows_dropped_and_counted(tmp_path, caplog):
    pts = _cloud(10)
    pts[2, 0] = np.nan
    pts[5, 2] = np.inf
    pts[7, 3] = -np.inf
    write_velodyne_bin(tmp_path / "n.bin", pts)
    back = read_points(tmp_path / "n.bin")
    assert back.shape == (7, 4)
    np.testing.assert_array_equal(back, pts[[0, 1, 3, 4, 6, 8, 9]])
    assert "dropped 3 point(s)" in caplog.text


def test_missing_and_folder_inputs(tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        read_points(tmp_path / "nope.bin")
    (tmp_path / "d.bin").mkdir()
    with pytest.raises(FormatError, match="is a folder"):
        read_points(tmp_path / "d.bin")
    with pytest.raises(FormatError, match="unknown point-cloud format"):
        read_points(tmp_path / "x.xyz")


def test_real_kitti_scan(kitti_object):
    pts = st.read_points(kitti_object / "velodyne" / "000000.bin")
    assert pts.shape[1] == 4 and 100_000 < pts.shape[0] < 130_000
    # Velodyne frame: ground ~1.73 m below the sensor, reflectance in [0, 1].
    assert -2.2 < np.percentile(pts[:, 2], 5) < -1.3
    assert pts[:, 3].min() >= 0 and pts[:, 3].max() <= 1


def test_real_nuscenes_lidar(nuscenes_demo):
    f = next(nuscenes_demo.glob("*LIDAR_TOP*.pcd.bin"))
    assert cloud_kind(f) == "nuscenes-bin"
    pts = read_lidar_pcd_bin(f)
    assert pts.shape == (34688, 5)
    assert set(np.unique(pts[:, 4]).astype(int)) <= set(range(32))


# -- .npy, PCD and PLY formats ---------------------------------------------------------------------
def test_npy_round_trip_and_bad_npy(tmp_path):
    pts = _cloud(20, 5)
    write_points(tmp_path / "a.npy", pts)
    np.testing.assert_array_equal(read_points(tmp_path / "a.npy"), pts)
    np.save(tmp_path / "b.npy", np.zeros((3, 2)))
    with pytest.raises(FormatError, match="N, C>=3"):
        read_points(tmp_path / "b.npy")
    (tmp_path / "c.npy").write_bytes(b"garbage")
    with pytest.raises(FormatError, match="not a valid .npy"):
        read_points(tmp_path / "c.npy")


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_pcd_ply_round_trip_keeps_attributes(tmp_path, suffix):
    pts = _cloud(50, 4)
    write_points(tmp_path / f"a{suffix}", pts)
    back = read_points(tmp_path / f"a{suffix}")
    assert back.shape == (50, 4)
    np.testing.assert_array_equal(back, pts)


def test_pcd_ply_corrupt_and_empty(tmp_path):
    (tmp_path / "e.ply").write_bytes(b"")
    with pytest.raises(FormatError, match="empty"):
        read_points(tmp_path / "e.ply")
    (tmp_path / "c.ply").write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(FormatError):
        read_points(tmp_path / "c.ply")


def test_import_is_light():
    import subprocess
    import sys

    code = (
        "import sys, sparsetools; sparsetools.read_points; sparsetools.Calibration;"
        "print(','.join(m for m in ('numba', 'open3d', 'torch', 'dask') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


# -- nuScenes radar PCD ------------------------------------------------------------------------------
def _radar(n=30, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.zeros((n, 18), np.float64)
    pts[:, :3] = rng.uniform([-50, -50, -1], [50, 50, 1], (n, 3)).astype(np.float32)
    pts[:, 3] = rng.integers(0, 8, n)  # dyn_prop
    pts[:, 4] = np.arange(n)  # id
    pts[:, 5] = rng.normal(size=n).astype(np.float32)
    pts[:, 11] = rng.choice([3, 3, 3, 1], n)  # ambig_state
    pts[:, 14] = rng.choice([0, 0, 0, 4], n)  # invalid_state
    return pts


def test_radar_pcd_round_trip_unfiltered(tmp_path):
    pts = _radar()
    write_radar_pcd(tmp_path / "r.pcd", pts)
    assert cloud_kind(tmp_path / "r.pcd") == "radar-pcd"
    back = read_radar_pcd(tmp_path / "r.pcd", filters=RadarFilter.none())
    assert back.shape == (30, 18)
    np.testing.assert_array_equal(back, pts.astype(np.float32))
    # 43 bytes per point: the packed nuScenes layout.
    header_len = (tmp_path / "r.pcd").read_bytes().index(b"DATA binary\n") + len("DATA binary\n")
    assert (tmp_path / "r.pcd").stat().st_size - header_len == 30 * 43


def test_radar_default_filters_match_devkit_rules(tmp_path):
    pts = _radar(200, seed=3)
    write_radar_pcd(tmp_path / "r.pcd", pts)
    back = read_points(tmp_path / "r.pcd")  # default filters on
    keep = (pts[:, 14] == 0) & (pts[:, 3] <= 6) & (pts[:, 11] == 3)
    np.testing.assert_array_equal(back, pts[keep].astype(np.float32))
    assert 0 < back.shape[0] < 200


def test_radar_truncated_and_wrong_header(tmp_path):
    write_radar_pcd(tmp_path / "r.pcd", _radar(10))
    data = (tmp_path / "r.pcd").read_bytes()
    (tmp_path / "t.pcd").write_bytes(data[:-5])
    with pytest.raises(FormatError, match="truncated"):
        read_radar_pcd(tmp_path / "t.pcd")
    (tmp_path / "h.pcd").write_bytes(b"VERSION 0.7\nFIELDS x y z\n")
    with pytest.raises(FormatError, match="no DATA line"):
        read_radar_pcd(tmp_path / "h.pcd")


def test_radar_fields_constant():
    assert len(RADAR_FIELDS) == 18 and RADAR_FIELDS[:3] == ["x", "y", "z"]


# -- nuScenes tables --------------------------------------------------------------------------------
def test_quaternion_matches_axis_angle():
    ang = 0.3
    q = [np.cos(ang / 2), 0, 0, np.sin(ang / 2)]  # rotation about z
    R = quaternion_to_matrix(q)
    np.testing.assert_allclose(
        R, [[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]], atol=1e-12
    )


def _write_tables(root, version="v1.0-mini"):
    d = root / version
    d.mkdir(parents=True)
    tables = {
        "sensor": [{"token": "s_r", "channel": "RADAR_FRONT", "modality": "radar"}],
        "calibrated_sensor": [
            {
                "token": "cs_r",
                "sensor_token": "s_r",
                "translation": [3.4, 0, 0.5],
                "rotation": [1, 0, 0, 0],
                "camera_intrinsic": [],
            }
        ],
        "ego_pose": [
            {
                "token": f"ep{i}",
                "translation": [i * 1.0, 0, 0],
                "rotation": [1, 0, 0, 0],
                "timestamp": i,
            }
            for i in range(3)
        ],
        "sample": [{"token": "smp", "timestamp": 2, "scene_token": "sc", "prev": "", "next": ""}],
        "sample_data": [
            {
                "token": f"sd{i}",
                "sample_token": "smp",
                "ego_pose_token": f"ep{i}",
                "calibrated_sensor_token": "cs_r",
                "filename": f"sweeps/RADAR_FRONT/{i}.pcd",
                "is_key_frame": i == 2,
                "prev": f"sd{i - 1}" if i else "",
                "next": "",
                "timestamp": i,
            }
            for i in range(3)
        ],
    }
    for name, rows in tables.items():
        (d / f"{name}.json").write_text(json.dumps(rows))


def test_tables_keyframe_and_sweeps(tmp_path):
    _write_tables(tmp_path)
    t = NuScenesTables(tmp_path, "v1.0-mini")
    key = t.sample_data("smp", "RADAR_FRONT")
    assert key["token"] == "sd2"
    assert [s["token"] for s in t.sweeps(key, 5)] == ["sd2", "sd1", "sd0"]
    assert t.T_global_from_ego(t.get("sample_data", "sd1"))[0, 3] == 1.0
    assert t.T_ego_from_sensor(key)[2, 3] == 0.5
    assert t.path(key) == tmp_path / "sweeps/RADAR_FRONT/2.pcd"
    with pytest.raises(FormatError, match="no key frame"):
        t.sample_data("smp", "CAM_FRONT")


def test_tables_missing_folder_and_table(tmp_path):
    with pytest.raises(FormatError, match="check --nuscenes-version"):
        NuScenesTables(tmp_path, "v1.0-mini")
    _write_tables(tmp_path)
    os.remove(tmp_path / "v1.0-mini" / "ego_pose.json")
    with pytest.raises(FormatError, match="ego_pose.json: missing"):
        NuScenesTables(tmp_path, "v1.0-mini")


# -- depth PNG and images ----------------------------------------------------------------------------
def test_depth_png_round_trip_quantisation(tmp_path):
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 200, (37, 53)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.7] = 0
    clipped = st.write_depth_png(tmp_path / "d.png", depth)
    assert clipped == 0
    back = st.read_depth_png(tmp_path / "d.png")
    assert back.dtype == np.float32 and back.shape == depth.shape
    np.testing.assert_array_equal(back > 0, depth > 0)
    assert np.abs(back - depth).max() <= 0.5 / 256 + 1e-6
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    np.testing.assert_array_equal(raw, np.rint(depth.astype(np.float64) * 256).astype(np.uint16))


def test_depth_png_clipping_and_invalid_values(tmp_path, caplog):
    depth = np.array([[0, -1, np.nan, np.inf], [300.0, 255.99, 1e-4, 1.0]], np.float32)
    clipped = st.write_depth_png(tmp_path / "d.png", depth)
    assert clipped == 2  # 300 m (> 65535/256) and 1e-4 m (rounds to 0)
    raw = cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(raw, [[0, 0, 0, 0], [65535, 65533, 1, 256]])
    assert "clipped" in caplog.text


@pytest.mark.parametrize("kind", ["8bit", "rgb16", "rgb8"])
def test_depth_png_rejects_8bit_and_colour(tmp_path, kind):
    arr = {
        "8bit": np.full((4, 4), 200, np.uint8),
        "rgb16": np.full((4, 4, 3), 2000, np.uint16),
        "rgb8": np.full((4, 4, 3), 20, np.uint8),
    }[kind]
    cv2.imwrite(str(tmp_path / "d.png"), arr)
    with pytest.raises(FormatError, match="uint16|channel"):
        st.read_depth_png(tmp_path / "d.png")


def test_corrupt_and_empty_png(tmp_path):
    (tmp_path / "e.png").write_bytes(b"")
    with pytest.raises(FormatError, match="empty file"):
        st.read_depth_png(tmp_path / "e.png")
    st.write_depth_png(tmp_path / "d.png", np.ones((50, 50), np.float32))
    data = (tmp_path / "d.png").read_bytes()
    (tmp_path / "t.png").write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="cannot decode"):
        st.read_depth_png(tmp_path / "t.png")
    (tmp_path / "j.jpg").write_bytes(b"\xff\xd8\xff\xe0garbage")
    with pytest.raises(FormatError, match="cannot decode"):
        st.read_image(tmp_path / "j.jpg")


def _png_header_only(w, h):
    ihdr = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    return (
        b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))
    )


def test_decompression_bomb_refused_before_decoding(tmp_path):
    (tmp_path / "bomb.png").write_bytes(_png_header_only(100_000, 100_000))
    with pytest.raises(FormatError, match="above the limit"):
        st.read_depth_png(tmp_path / "bomb.png")
    with pytest.raises(FormatError, match="above the limit"):
        st.read_image(tmp_path / "bomb.png")


def test_image_header_size_png_and_jpeg():
    _, png = cv2.imencode(".png", np.zeros((7, 11, 3), np.uint8))
    _, jpg = cv2.imencode(".jpg", np.zeros((13, 17, 3), np.uint8))
    assert image_header_size(png.tobytes()) == (11, 7)
    assert image_header_size(jpg.tobytes()) == (17, 13)
    assert image_header_size(b"nothing") is None


def test_image_is_rgb_not_bgr(tmp_path):
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 255  # pure red
    st.write_image(tmp_path / "r.png", rgb)
    bgr = cv2.imread(str(tmp_path / "r.png"))
    assert bgr[0, 0].tolist() == [0, 0, 255]
    np.testing.assert_array_equal(st.read_image(tmp_path / "r.png"), rgb)


def test_image_grey_is_replicated_and_16bit_refused(tmp_path):
    cv2.imwrite(str(tmp_path / "g.png"), np.full((3, 3), 77, np.uint8))
    img = st.read_image(tmp_path / "g.png")
    assert img.shape == (3, 3, 3) and (img == 77).all()
    cv2.imwrite(str(tmp_path / "d.png"), np.full((3, 3), 7000, np.uint16))
    with pytest.raises(FormatError, match="depth map"):
        st.read_image(tmp_path / "d.png")


def test_real_images(kitti_object, nuscenes_demo):
    img = st.read_image(kitti_object / "image_2" / "000000.png")
    # KITTI object frames differ in size (000000 is 1224x370).
    assert img.shape == (370, 1224, 3) and img.dtype == np.uint8
    cam = st.read_image(next(nuscenes_demo.glob("*CAM_FRONT__*.jpg")))
    assert cam.shape == (900, 1600, 3)


def test_real_depth_gt(real_dir):
    d = st.read_depth_png(real_dir / "kitti-depth-gt-metric3d" / "depth" / "0000000005.png")
    assert d.ndim == 2 and d.max() > 20 and 0.01 < (d > 0).mean() < 0.5


# -- atomic writes ----------------------------------------------------------------------------------
def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_refuses_overwrite_and_file_in_the_way(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"x")
    with pytest.raises(OutputError, match="exists"):
        with atomic_path(tmp_path / "a.bin", overwrite=False):
            pass
    assert (tmp_path / "a.bin").read_bytes() == b"x"
    (tmp_path / "file").write_bytes(b"")
    with pytest.raises(OutputError, match="a file is in the way"):
        with atomic_path(tmp_path / "file" / "x.png"):
            pass


def test_atomic_write_bytes_round_trip_permissions_and_folders(tmp_path):
    old = os.umask(0o027)
    try:
        atomic_write_bytes(tmp_path / "new" / "deep" / "a.png", b"abc" * 100_000)
        atomic_write_bytes(tmp_path / "new" / "deep" / "a.png", memoryview(b"second"))
    finally:
        os.umask(old)
    target = tmp_path / "new" / "deep" / "a.png"
    assert target.read_bytes() == b"second"
    assert target.stat().st_mode & 0o777 == 0o640
    assert [p.name for p in target.parent.iterdir()] == ["a.png"]  # no temporary left


def test_atomic_write_bytes_refuses_empty_data_and_file_in_the_way(tmp_path):
    with pytest.raises(OutputError, match="no data"):
        atomic_write_bytes(tmp_path / "a.png", b"")
    atomic_write_bytes(tmp_path / "empty.bin", b"")  # an empty KITTI cloud is legitimate
    assert (tmp_path / "empty.bin").read_bytes() == b""
    (tmp_path / "file").write_bytes(b"")
    with pytest.raises(OutputError, match="a file is in the way"):
        atomic_write_bytes(tmp_path / "file" / "x.png", b"x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.bin", "file"]


def test_atomic_write_bytes_full_disk_leaves_the_old_file(tmp_path, monkeypatch):
    import errno

    target = tmp_path / "a.png"
    target.write_bytes(b"old")

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(OutputError, match=r"no space left on device while writing .*a\.png"):
        atomic_write_bytes(target, b"new")
    monkeypatch.undo()
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]


def test_remove_stale_temporaries(tmp_path):
    (tmp_path / f"{TMP_PREFIX}abc.png").write_bytes(b"x")
    (tmp_path / "keep.png").write_bytes(b"x")
    assert remove_stale_temporaries(tmp_path) == 1
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


def test_radar_writer_refuses_out_of_range_integer_fields(tmp_path):
    pts = _radar(3)
    pts[0, 3] = 300  # dyn_prop is int8
    with pytest.raises(FormatError, match="dyn_prop"):
        write_radar_pcd(tmp_path / "r.pcd", pts)
    assert not (tmp_path / "r.pcd").exists()


def test_atomic_outputs_get_normal_permissions(tmp_path):
    old = os.umask(0o022)
    try:
        write_velodyne_bin(tmp_path / "a.bin", _cloud(2))
    finally:
        os.umask(old)
    assert (tmp_path / "a.bin").stat().st_mode & 0o777 == 0o644


def test_reading_a_small_file_reserves_its_size_not_the_limit(tmp_path):
    """read_regular_file under a 1 GiB address-space limit reads a small file whose limit is
    4 GiB (a depth map's): it reserved the limit for every file before, and failed there."""
    import subprocess
    import sys

    (tmp_path / "m.png").write_bytes(b"x" * 1000)
    (tmp_path / "big").write_bytes(b"y" * 3000)
    code = (
        "import resource, sys\n"
        "from sparsetools.errors import FormatError\n"
        "from sparsetools.io.sidecar import read_regular_file\n"
        "resource.setrlimit(resource.RLIMIT_AS, (1 << 30, resource.RLIM_INFINITY))\n"
        f"d = read_regular_file({str(tmp_path / 'm.png')!r}, what='map', max_bytes=1 << 32)\n"
        "print(len(d))\n"
        "try:\n"
        f"    read_regular_file({str(tmp_path / 'big')!r}, what='map', max_bytes=2000)\n"
        "except FormatError as e:\n"
        "    print('refused', 'limit 2000' in str(e))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout.split() == ["1000", "refused", "True"]
