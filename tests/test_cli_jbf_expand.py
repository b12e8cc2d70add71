"""``sparsetools jbf-expand``: inputs (PNG, .pcd + calib), outputs, resize, LiDAR table, errors."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.calibration import Calibration
from sparsetools.cli.main import cli
from sparsetools.io.calib import write_json_calib
from sparsetools.io.image import read_depth_png, read_image, write_depth_png, write_image
from sparsetools.io.nuscenes import RADAR_FIELDS, write_radar_pcd
from sparsetools.ops.jbf import height_extend, jbf_expand
from sparsetools.pipeline.jbf_expand import resize_sparse_depth

W, H = 96, 64
F = 80.0


def run(*args):
    return CliRunner().invoke(cli, ["jbf-expand", *[str(a) for a in args]])


def assert_clean_failure(result, code, match):
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    if code == 1:
        lines = [ln for ln in result.stderr.splitlines() if ln.startswith("Error:")]
        assert len(lines) == 1, result.stderr
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


def make_frame(rng):
    """A blocky image (objects of one colour), random seeds, LiDAR = dense truth.

    The colours' luminances (90 background; 240, 10, 196, 163) differ by more than the
    range kernel's reach (about 24 levels at sigma_r 10), as distinct objects usually do.
    """
    img = np.full((H, W, 3), 90, np.uint8)
    truth = np.full((H, W), 30.0, np.float32)
    colours = [(240, 240, 240), (10, 10, 10), (200, 220, 60), (250, 150, 0)]
    for colour in colours:
        y, x = rng.integers(0, H - 16), rng.integers(0, W - 20)
        img[y : y + 16, x : x + 20] = colour
        truth[y : y + 16, x : x + 20] = rng.uniform(4, 20)
    radar = np.zeros((H, W), np.float32)
    ys = rng.integers(0, H, 12)
    xs = rng.integers(0, W, 12)
    radar[ys, xs] = truth[ys, xs] + rng.normal(0, 0.1, 12).astype(np.float32)
    return img, radar, truth


@pytest.fixture
def scene(tmp_path):
    """Two frames: images/, radar/ (depth PNGs), lidar/ (depth PNGs)."""
    rng = np.random.default_rng(0)
    root = tmp_path / "in"
    for stem in ("000000", "000001"):
        img, radar, truth = make_frame(rng)
        write_image(root / "images" / f"{stem}.png", img)
        write_depth_png(root / "radar" / f"{stem}.png", radar)
        write_depth_png(root / "lidar" / f"{stem}.png", truth)
    return root


def expected(root: Path, stem: str, **kw):
    radar = read_depth_png(root / "radar" / f"{stem}.png")
    img = read_image(root / "images" / f"{stem}.png")
    return radar, img, jbf_expand(radar, img, fx=F, fy=F, **kw)


def as_png_depth(depth):
    return np.rint(depth.astype(np.float64) * 256).astype(np.uint16)


# -- outputs ------------------------------------------------------------------------------------


def test_png_inputs_write_depth_and_confidence(scene, tmp_path):
    out = tmp_path / "out"
    before = digest(scene)
    r = run(scene / "radar", "--image", scene / "images", "--fx", F, "--fy", F, "-o", out)
    assert r.exit_code == 0, r.stderr
    assert files_under(out) == ["000000.png", "000000_conf.png", "000001.png", "000001_conf.png"]
    for stem in ("000000", "000001"):
        radar, _, (depth, conf) = expected(scene, stem)
        got = cv2.imread(str(out / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(got, as_png_depth(depth))
        got_conf = cv2.imread(str(out / f"{stem}_conf.png"), cv2.IMREAD_UNCHANGED)
        assert got_conf.dtype == np.uint16
        np.testing.assert_array_equal(got_conf, np.rint(conf.astype(np.float64) * 65535.0))
        assert np.all(got_conf[radar > 0] == 65535)
        assert np.count_nonzero(depth) > 20 * np.count_nonzero(radar)
    assert "processed         2" in r.stdout
    assert digest(scene) == before
    # Resume: nothing to do; --overwrite recomputes.
    r = run(scene / "radar", "--image", scene / "images", "--fx", F, "--fy", F, "-o", out)
    assert r.exit_code == 0 and "skipped existing  2" in r.stdout


def test_options_reach_the_library_and_npy_confidence(scene, tmp_path):
    out = tmp_path / "out"
    args = [
        "--kernel",
        "range",
        "--range-metric",
        "rgb",
        "--conflict",
        "max-confidence",
        "--sigma-s",
        "7",
        "--sigma-r",
        "25",
        "--threshold",
        "0.2",
        "--window",
        "1x2",
    ]
    r = run(
        scene / "radar" / "000001.png",
        "--image",
        scene / "images" / "000001.png",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
        "--conf-format",
        "npy",
        *args,
    )
    assert r.exit_code == 0, r.stderr
    assert files_under(out) == ["000001.png", "000001_conf.npy"]
    _, _, (depth, conf) = expected(
        scene,
        "000001",
        kernel="range",
        range_metric="rgb",
        conflict="max-confidence",
        sigma_s=7.0,
        sigma_r=25.0,
        threshold=0.2,
        window_m=(1.0, 2.0),
    )
    np.testing.assert_array_equal(np.load(out / "000001_conf.npy"), conf)
    np.testing.assert_array_equal(
        cv2.imread(str(out / "000001.png"), cv2.IMREAD_UNCHANGED), as_png_depth(depth)
    )


def test_no_confidence_and_height_extend(scene, tmp_path):
    out = tmp_path / "out"
    r = run(
        scene / "radar",
        "--image",
        scene / "images",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
        "--method",
        "height-extend",
        "--no-confidence",
    )
    assert r.exit_code == 0, r.stderr
    assert files_under(out) == ["000000.png", "000001.png"]
    radar = read_depth_png(scene / "radar" / "000000.png")
    np.testing.assert_array_equal(
        cv2.imread(str(out / "000000.png"), cv2.IMREAD_UNCHANGED),
        as_png_depth(height_extend(radar, fy=F)),
    )


def test_workers_give_identical_bytes(scene, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    base = [scene / "radar", "--image", scene / "images", "--fx", F, "--fy", F]
    assert run(*base, "-o", a).exit_code == 0
    assert run(*base, "-o", b, "--workers", "2").exit_code == 0
    assert digest(a).values() and list(digest(a).values()) == list(digest(b).values())


def test_pcd_inputs_are_projected_with_the_calibration(tmp_path):
    rng = np.random.default_rng(3)
    img, _, _ = make_frame(rng)
    K = np.array([[F, 0, W / 2 - 0.5], [0, F, H / 2 - 0.5], [0, 0, 1]])
    # Radar frame: x forward, y left, z up (nuScenes); camera: x right, y down, z forward.
    T = np.array([[0, -1, 0, 0.1], [0, 0, -1, 0.3], [1, 0, 0, 0.5], [0, 0, 0, 1.0]])
    calib = Calibration(K=K, T_cam_from_sensor=T, width=W, height=H)
    pts = np.zeros((30, len(RADAR_FIELDS)), np.float32)
    pts[:, 0] = rng.uniform(4, 25, 30)
    pts[:, 1] = rng.uniform(-4, 4, 30)
    pts[:, 2] = rng.uniform(-0.5, 0.5, 30)
    pts[:, RADAR_FIELDS.index("ambig_state")] = 3  # pass the devkit's default filters
    root = tmp_path / "in"
    write_radar_pcd(root / "radar" / "000007.pcd", pts)
    write_radar_pcd(root / "radar" / "000007_sweep0.pcd", pts[:10])  # a sweep of the frame
    write_json_calib(root / "calib" / "000007.json", calib)
    write_image(root / "images" / "000007.png", img)
    out = tmp_path / "out"
    r = run(root / "radar", "--calib", root / "calib", "--image", root / "images", "-o", out)
    assert r.exit_code == 0, r.stderr
    assert files_under(out) == ["000007.png", "000007_conf.png"]
    # Independent projection: camera points, rint pixel, nearest depth.
    cam = pts[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    u = np.rint(F * cam[:, 0] / cam[:, 2] + K[0, 2]).astype(int)
    v = np.rint(F * cam[:, 1] / cam[:, 2] + K[1, 2]).astype(int)
    radar = np.zeros((H, W), np.float32)
    for ui, vi, z in zip(u, v, cam[:, 2].astype(np.float32), strict=True):
        if 0 <= ui < W and 0 <= vi < H and (radar[vi, ui] == 0 or z < radar[vi, ui]):
            radar[vi, ui] = z
    assert np.count_nonzero(radar) > 10
    depth, _ = jbf_expand(radar, img, fx=F, fy=F)
    np.testing.assert_array_equal(
        cv2.imread(str(out / "000007.png"), cv2.IMREAD_UNCHANGED), as_png_depth(depth)
    )


def test_resize_keeps_points_and_scales_focal_lengths(scene, tmp_path):
    out = tmp_path / "out"
    r = run(
        scene / "radar" / "000000.png",
        "--image",
        scene / "images" / "000000.png",
        "--fx",
        F,
        "--fy",
        F,
        "--resize",
        "0.5",
        "-o",
        out,
    )
    assert r.exit_code == 0, r.stderr
    got = read_depth_png(out / "000000.png")
    assert got.shape == (H // 2, W // 2)
    radar = read_depth_png(scene / "radar" / "000000.png")
    small = resize_sparse_depth(radar, 0.5, (W // 2, H // 2))
    img = cv2.resize(
        read_image(scene / "images" / "000000.png"), (W // 2, H // 2), interpolation=cv2.INTER_AREA
    )
    depth, _ = jbf_expand(small, img, fx=F / 2, fy=F / 2)
    np.testing.assert_array_equal(as_png_depth(got), as_png_depth(depth))


def test_resize_sparse_depth_moves_points_and_keeps_the_nearest():
    depth = np.zeros((8, 10), np.float32)
    depth[0, 0] = 5.0
    depth[7, 9] = 7.0
    depth[2, 2] = 9.0
    depth[2, 3] = 4.0  # lands on the same pixel as (2, 2) at half size
    depth[3, 3] = np.nan
    small = resize_sparse_depth(depth, 0.5, (5, 4))
    assert small.shape == (4, 5)
    assert small[0, 0] == 5.0 and small[3, 4] == 7.0 and small[1, 1] == 4.0
    assert np.count_nonzero(small) == 3 and np.all(np.isfinite(small))
    big = resize_sparse_depth(depth, 2.0, (20, 16))
    # Never interpolated: the same depths, one pixel each, at 2 (u + 0.5) - 0.5 rounded.
    assert sorted(big[big > 0].tolist()) == [4.0, 5.0, 7.0, 9.0]
    assert big[0, 0] == 5.0 and big[4, 4] == 9.0 and big[4, 6] == 4.0  # rint(4.5) = 4 (even)
    assert big[14, 18] == 7.0


# -- intrinsic-error table ----------------------------------------------------------------------


def test_lidar_table_per_frame_and_mean(scene, tmp_path):
    out = tmp_path / "out"
    r = run(
        scene / "radar",
        "--image",
        scene / "images",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
        "--lidar",
        scene / "lidar",
    )
    assert r.exit_code == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].startswith("intrinsic error against LiDAR (depth <= 80 m)")
    for stem in ("000000", "000001"):
        for method in ("raw", "jbf", "height-extend"):
            assert any(ln.split()[:2] == [stem, method] for ln in lines), (stem, method)
    assert sum(ln.startswith("mean of 2") for ln in lines) == 3
    r = run(
        scene / "radar",
        "--image",
        scene / "images",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
        "--lidar",
        scene / "lidar",
        "--json",
        "--overwrite",
    )
    summary = json.loads(r.stdout)
    table = summary["intrinsic_error"]
    from sparsetools.ops.intrinsic import intrinsic_error

    radar, _, (depth, _) = expected(scene, "000000")
    lidar = read_depth_png(scene / "lidar" / "000000.png")
    assert table["frames"]["000000"]["jbf"] == pytest.approx(intrinsic_error(depth, lidar))
    assert table["frames"]["000000"]["raw"] == pytest.approx(intrinsic_error(radar, lidar))
    ext = intrinsic_error(height_extend(radar, fy=F), lidar)
    assert table["frames"]["000000"]["height-extend"] == pytest.approx(ext)
    mean_rmse = np.mean([table["frames"][s]["jbf"]["rmse"] for s in ("000000", "000001")])
    assert table["mean"]["jbf"]["rmse"] == pytest.approx(mean_rmse)
    # On blocky objects the expansion is far denser than the radar and close to the truth.
    assert table["mean"]["jbf"]["points"] > 20 * table["mean"]["raw"]["points"]
    assert table["mean"]["jbf"]["rmse"] < table["mean"]["height-extend"]["rmse"]
    assert summary["expansion_factor"] > 20


def test_synthetic_street_end_to_end(tmp_path):
    from sparsetools.synth import generate_scene

    root = tmp_path / "scene"
    generate_scene(root, seed=1, frames=1, width=621, height=188, underwater_frames=0)
    out = tmp_path / "out"
    r = run(
        root / "radar",
        "--calib",
        root / "calib_radar",
        "--image",
        root / "image_2",
        "--lidar",
        root / "depth_gt",
        "-o",
        out,
        "--json",
    )
    assert r.exit_code == 0, r.stderr
    table = json.loads(r.stdout)["intrinsic_error"]["frames"]["000000"]
    assert table["jbf"]["points"] > 100 * table["raw"]["points"] > 0
    assert table["jbf"]["rmse"] < table["height-extend"]["rmse"]
    assert files_under(out) == ["000000.png", "000000_conf.png"]


# -- bad input ----------------------------------------------------------------------------------


def test_sizes_differ(scene, tmp_path):
    out = tmp_path / "out"
    img = np.zeros((H + 2, W, 3), np.uint8)
    write_image(tmp_path / "big.png", img)
    r = run(
        scene / "radar" / "000000.png",
        "--image",
        tmp_path / "big.png",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
    )
    assert_clean_failure(r, 1, "same size")
    assert files_under(out) == []


def test_eight_bit_radar(scene, tmp_path):
    out = tmp_path / "out"
    (tmp_path / "r").mkdir()
    cv2.imwrite(str(tmp_path / "r" / "000000.png"), np.full((H, W), 20, np.uint8))
    r = run(
        tmp_path / "r" / "000000.png",
        "--image",
        scene / "images" / "000000.png",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
    )
    assert_clean_failure(r, 1, "8-bit")
    assert files_under(out) == []


def test_empty_radar_map_gives_empty_output(scene, tmp_path):
    out = tmp_path / "out"
    write_depth_png(tmp_path / "r" / "000000.png", np.zeros((H, W), np.float32))
    r = run(tmp_path / "r", "--image", scene / "images", "--fx", F, "--fy", F, "-o", out)
    assert r.exit_code == 0, r.stderr
    assert not read_depth_png(out / "000000.png").any()
    assert not cv2.imread(str(out / "000000_conf.png"), cv2.IMREAD_UNCHANGED).any()


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--fx", "0", "--fy", "80"], "'--fx': must be a finite number > 0"),
        (["--fx", "80", "--fy", "-3"], "'--fy': must be a finite number > 0"),
        (["--fx", "80", "--fy", "80", "--sigma-s", "0"], "sigma-s"),
        (["--fx", "80", "--fy", "80", "--sigma-r", "-1"], "sigma-r"),
        (["--fx", "80", "--fy", "80", "--threshold", "0"], "threshold"),
        (["--fx", "80", "--fy", "80", "--threshold", "1.5"], "threshold"),
        (["--fx", "80", "--fy", "80", "--window", "2x0"], "window"),
        (["--fx", "80", "--fy", "80", "--window", "big"], "window"),
        (["--fx", "80", "--fy", "80", "--kernel", "box"], "kernel"),
        (["--fx", "80", "--fy", "80", "--resize", "0"], "resize"),
        (["--fx", "80"], "--fy"),
        ([], "--calib"),
    ],
)
def test_usage_errors_exit_2(scene, tmp_path, extra, match):
    out = tmp_path / "out"
    r = run(scene / "radar", "--image", scene / "images", "-o", out, *extra)
    assert_clean_failure(r, 2, match)
    assert not out.exists()


def test_library_errors_exit_1_before_any_output(scene, tmp_path):
    out = tmp_path / "out"
    before = digest(scene)
    # One image for two frames.
    r = run(
        scene / "radar", "--image", scene / "images" / "000000.png", "--fx", F, "--fy", F, "-o", out
    )
    assert_clean_failure(r, 1, "is one file but 2 frames were given")
    # No image for a frame.
    (scene / "images" / "000001.png").rename(tmp_path / "moved.png")
    r = run(scene / "radar", "--image", scene / "images", "--fx", F, "--fy", F, "-o", out)
    assert_clean_failure(r, 1, "no image for frame 000001")
    (tmp_path / "moved.png").rename(scene / "images" / "000001.png")
    # A .pcd without calibration.
    pcd = tmp_path / "p" / "000000.pcd"
    write_radar_pcd(pcd, np.zeros((1, len(RADAR_FIELDS))))
    r = run(pcd, "--image", scene / "images" / "000000.png", "--fx", F, "--fy", F, "-o", out)
    assert_clean_failure(r, 1, "need --calib")
    # Not a radar file.
    (tmp_path / "x.txt").write_text("1 2 3")
    r = run(
        tmp_path / "x.txt",
        "--image",
        scene / "images" / "000000.png",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        out,
    )
    assert_clean_failure(r, 1, "not a radar input")
    # Output inside the input folder.
    r = run(
        scene / "radar",
        "--image",
        scene / "images",
        "--fx",
        F,
        "--fy",
        F,
        "-o",
        scene / "radar" / "out",
    )
    assert_clean_failure(r, 1, "inside the input folder")
    assert not out.exists() and not (scene / "radar" / "out").exists()
    assert digest(scene) == before


def test_calibration_for_another_image_size(scene, tmp_path):
    calib = Calibration(
        K=np.diag([F, F, 1.0]), T_cam_from_sensor=np.eye(4), width=W * 2, height=H * 2
    )
    write_json_calib(tmp_path / "c.json", calib)
    out = tmp_path / "out"
    r = run(
        scene / "radar" / "000000.png",
        "--image",
        scene / "images" / "000000.png",
        "--calib",
        tmp_path / "c.json",
        "-o",
        out,
    )
    assert_clean_failure(r, 1, f"is for {2 * W}x{2 * H} images")
    assert files_under(out) == []


@pytest.mark.real
def test_kitti_raw_calibration_folder_gives_the_focal_lengths(real_dir, tmp_path):
    root = real_dir / "kitti-depth-gt-metric3d"
    gt = read_depth_png(root / "depth" / "0000000005.png")
    radar = np.zeros_like(gt)
    ys, xs = np.nonzero(gt)
    radar[ys[::5000], xs[::5000]] = gt[ys[::5000], xs[::5000]]
    write_depth_png(tmp_path / "r" / "0000000005.png", radar)
    out = tmp_path / "out"
    r = run(
        tmp_path / "r",
        "--image",
        root / "rgb",
        "--calib",
        real_dir / "kitti-raw-calib-2011_09_26",
        "-o",
        out,
        "--no-confidence",
    )
    assert r.exit_code == 0, r.stderr
    rgb = read_image(root / "rgb" / "0000000005.png")
    depth, _ = jbf_expand(
        read_depth_png(tmp_path / "r" / "0000000005.png"), rgb, fx=721.5377, fy=721.5377
    )
    np.testing.assert_array_equal(
        cv2.imread(str(out / "0000000005.png"), cv2.IMREAD_UNCHANGED), as_png_depth(depth)
    )


def test_output_never_overwrites_an_input(scene, tmp_path):
    # Radar file and image both named 000000.png in one folder, output into that folder.
    flat = tmp_path / "flat"
    flat.mkdir()
    (flat / "000000.png").write_bytes((scene / "radar" / "000000.png").read_bytes())
    img = tmp_path / "img" / "000000.png"
    img.parent.mkdir()
    img.write_bytes((scene / "images" / "000000.png").read_bytes())
    before = digest(tmp_path)
    r = run(flat / "000000.png", "--image", img, "--fx", F, "--fy", F, "-o", img.parent)
    assert_clean_failure(r, 1, "000000.png would replace an input file")
    assert digest(tmp_path) == before
