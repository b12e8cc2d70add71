"""`dataset export --layout monodepth2-gt`: monodepth2's gt_depths.npz from a real KITTI raw
tree, read back as monodepth2 reads it and compared with a reference written here."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from _cli import one_line_error, run, summary
from sparsetools.ops.eigen_gt import eigen_depth_map

pytestmark = pytest.mark.real

DATE = "2011_09_26"
DRIVE = f"{DATE}_drive_0001_sync"
FRAMES = (4, 0, 7)  # split-file order, not sorted


@pytest.fixture(scope="module")
def raw_root(real_dir, tmp_path_factory) -> Path:
    """raw/2011_09_26/{calib, 2011_09_26_drive_0001_sync/{velodyne_points,image_02}/data}."""
    seq = real_dir / "kitti-raw-sequence-2011_09_26"
    root = tmp_path_factory.mktemp("raw")
    date = root / DATE
    date.mkdir()
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(seq / name, date / name)
    for sub, ext in (("velodyne_points", ".bin"), ("image_02", ".png")):
        folder = date / DRIVE / sub / "data"
        folder.mkdir(parents=True)
        for i in FRAMES:
            shutil.copy(seq / sub / "data" / f"{i:010d}{ext}", folder / f"{i:010d}{ext}")
    return root


def split_file(path: Path, frames=FRAMES, drive=DRIVE) -> Path:
    path.write_text("".join(f"{DATE}/{drive} {i:010d} l\n" for i in frames))
    return path


def load_like_monodepth2(gt_path: Path) -> np.ndarray:
    """What monodepth2's evaluate_depth.py does with the file."""
    return np.load(gt_path, fix_imports=True, encoding="latin1", allow_pickle=True)["data"]


def _calib_file(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in path.read_text().splitlines():
        key, _, value = line.partition(":")
        try:
            out[key] = np.array([float(x) for x in value.split()])
        except ValueError:
            pass  # calib_time: a date
    return out


def reference_map(raw: Path, frame: int, *, vel_depth: bool = True) -> np.ndarray:
    """monodepth2's generate_depth_map(calib_dir, velo_filename, 2, vel_depth), restated:
    x < 0 dropped, P_rect_02 @ R_rect_00 @ [R|T], round - 1, in-bounds, per pixel the point
    with the smallest stored value (first of a sort, not a scatter-min)."""
    cam = _calib_file(raw / DATE / "calib_cam_to_cam.txt")
    velo = _calib_file(raw / DATE / "calib_velo_to_cam.txt")
    velo2cam = np.vstack([np.hstack([velo["R"].reshape(3, 3), velo["T"][:, None]]), [0, 0, 0, 1]])
    rect = np.eye(4)
    rect[:3, :3] = cam["R_rect_00"].reshape(3, 3)
    P = cam["P_rect_02"].reshape(3, 4) @ rect @ velo2cam
    w, h = cam["S_rect_02"].astype(int)
    pts = np.fromfile(raw / DATE / DRIVE / "velodyne_points" / "data" / f"{frame:010d}.bin",
                      dtype=np.float32).reshape(-1, 4)  # fmt: skip
    pts = pts[pts[:, 0] >= 0].astype(np.float64)
    pts[:, 3] = 1.0
    im = (P @ pts.T).T
    im[:, :2] /= im[:, 2:3]
    value = pts[:, 0] if vel_depth else im[:, 2]
    u, v = np.round(im[:, 0]) - 1, np.round(im[:, 1]) - 1
    ok = (u >= 0) & (v >= 0) & (u < w) & (v < h)
    u, v, value = u[ok].astype(int), v[ok].astype(int), value[ok]
    order = np.argsort(value, kind="stable")
    flat = (v * w + u)[order]
    _, first = np.unique(flat, return_index=True)
    depth = np.zeros(h * w)
    depth[flat[first]] = value[order][first]
    depth[depth < 0] = 0
    return depth.reshape(h, w).astype(np.float32)


def test_gt_depths_round_trips_and_equals_the_reference(raw_root, tmp_path):
    out = tmp_path / "eigen"
    split = split_file(tmp_path / "test_files.txt")
    s = summary("dataset", "export", raw_root, "-o", out, "--layout", "monodepth2-gt",
                "--split-file", split)  # fmt: skip
    assert s["lines"] == s["maps"] == len(FRAMES) and s["sizes"] == {"1242x375": 3}
    data = load_like_monodepth2(out / "gt_depths.npz")
    assert data.dtype == object and data.shape == (len(FRAMES),)
    for gt, frame in zip(data, FRAMES, strict=True):  # the split file's order
        assert gt.dtype == np.float32 and gt.shape == (375, 1242)
        ref = reference_map(raw_root, frame)
        np.testing.assert_array_equal(gt, ref)
        assert 10_000 < np.count_nonzero(gt) < 30_000  # a 64-beam scan in the camera's view
    # the Velodyne x, not the camera z: ~0.28 m further (the LiDAR sits behind the camera)
    scan = raw_root / DATE / DRIVE / "velodyne_points" / "data" / "0000000004.bin"
    points = np.fromfile(scan, dtype=np.float32).reshape(-1, 4)
    z = eigen_depth_map(points, _projection(raw_root), (375, 1242), value="camera-z")
    np.testing.assert_allclose(z, reference_map(raw_root, 4, vel_depth=False), rtol=1e-6)
    both = (z > 0) & (data[0] > 0)
    assert 0.2 < float(np.median(data[0][both] - z[both])) < 0.35
    # rerun: up to date, the archive untouched
    mtime = (out / "gt_depths.npz").stat().st_mtime_ns
    again = summary("dataset", "export", raw_root, "-o", out, "--layout", "monodepth2-gt",
                    "--split-file", split)  # fmt: skip
    assert again["maps"] == 0 and again["up_to_date"] is True
    assert (out / "gt_depths.npz").stat().st_mtime_ns == mtime
    assert sorted(p.name for p in out.iterdir()) == [".sparsetools", "gt_depths.npz"]


def _projection(raw: Path) -> np.ndarray:
    from sparsetools.io.calib import read_kitti_raw_calib

    return read_kitti_raw_calib(raw / DATE).projection


def test_camera_z_option_and_another_setting_refused(raw_root, tmp_path):
    out = tmp_path / "eigen"
    split = split_file(tmp_path / "test_files.txt", frames=(0,))
    s = summary("dataset", "export", raw_root, "-o", out, "--layout", "monodepth2-gt",
                "--split-file", split, "--depth-value", "camera-z")  # fmt: skip
    assert s["value"] == "camera-z"
    (gt,) = load_like_monodepth2(out / "gt_depths.npz")
    np.testing.assert_allclose(gt, reference_map(raw_root, 0, vel_depth=False), rtol=1e-6)
    r = run("dataset", "export", raw_root, "-o", out, "--layout", "monodepth2-gt",
            "--split-file", split)  # fmt: skip
    assert "--depth-value" in one_line_error(r)


def test_missing_lines_are_refused_naming_them(raw_root, tmp_path):
    split = tmp_path / "test_files.txt"
    split.write_text(
        f"{DATE}/{DRIVE} 0000000004 l\n{DATE}/{DRIVE} 0000000009 l\n"
        f"{DATE}/{DATE}_drive_0002_sync 0000000001 r\n"
    )
    r = run("dataset", "export", raw_root, "-o", tmp_path / "out", "--layout", "monodepth2-gt",
            "--split-file", split)  # fmt: skip
    line = one_line_error(r)
    assert "2 of the 3 lines" in line and f"{DRIVE} 0000000009 l" in line
    assert f"{DATE}_drive_0002_sync 0000000001 r" in line
    assert not (tmp_path / "out").exists()
    r = run("dataset", "export", raw_root, "-o", tmp_path / "out", "--layout", "monodepth2-gt")
    assert r.exit_code == 2 and "one --split-file" in r.output


def test_eigen_depth_map_keeps_the_nearest_and_drops_what_monodepth2_drops():
    """Hand-made points on a 3x3 image, a camera looking along x (f = 1, centre (1, 1)):
    u = y / x + 1, v = z / x + 1, w = x."""
    M = np.array([[1.0, 1, 0, 0], [1, 0, 1, 0], [1, 0, 0, 0]])
    pts = np.array([[5.0, 0, 0], [4.0, 0, 0], [-3.0, 0, 0], [2.0, 2.0, 0], [6.0, 6.0, 6.0]])
    d = eigen_depth_map(pts, M, (3, 3))  # offset -1: pixel (round(u) - 1, round(v) - 1)
    expect = np.zeros((3, 3), np.float32)
    expect[0, 0] = 4.0  # the nearer of 5 and 4; x < 0 dropped
    expect[0, 1] = 2.0  # u = 2/2 + 1 = 2 -> 1
    expect[1, 1] = 6.0  # u = v = 6/6 + 1 = 2 -> 1
    np.testing.assert_array_equal(d, expect)
    assert not eigen_depth_map(np.zeros((0, 3)), M, (3, 3)).any()
