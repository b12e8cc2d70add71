"""Ground truth of the one-command routes (issue 25, part 3): ``dataset kitti-raw --gt-method
scan|accumulated``, ``--filter-occluded``, the stereo check, ``dataset nuscenes --gt-sweeps N
--filter-occluded``, and the per-sample ``gt_method`` of the manifest.

The stereo check is tested on a synthetic rectified pair whose disparity is known by
construction (two textured fronto-parallel layers); the real KITTI sequence has no image_03.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from _cli import run, summary

sys.path.insert(0, str(Path(__file__).parent))

DATE = "2011_09_26"
DRIVE = f"{DATE}_drive_0001_sync"
FRAMES = range(3, 8)  # 5 frames of the real sequence
FX, BASELINE = 721.5377, 0.5327254279298227  # P_rect_02 / P_rect_03 of 2011_09_26


def rows(ds: Path) -> list[dict]:
    import pyarrow.parquet as pq

    return pq.read_table(ds / "manifest.parquet").to_pylist()


def gt_maps(ds: Path) -> dict[str, np.ndarray]:
    from sparsetools.io.image import read_depth_png

    return {r["id"]: read_depth_png(ds / r["gt_path"]) for r in rows(ds)}


def sample_params(ds: Path) -> dict[str, dict]:
    return {r["id"]: json.loads(r["generation_params"])["sample"] for r in rows(ds)}


def pixels(mask: np.ndarray) -> set[tuple[int, int]]:
    """The (row, column) of the True pixels."""
    return {(int(v), int(u)) for v, u in np.argwhere(mask)}


def _raw_tree(real_dir: Path, root: Path, frames) -> Path:
    seq = real_dir / "kitti-raw-sequence-2011_09_26"
    date = root / DATE
    date.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(seq / name, date / name)
    for i in frames:
        for sub, ext in (("velodyne_points", ".bin"), ("image_02", ".png")):
            folder = date / DRIVE / sub / "data"
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copy(seq / sub / "data" / f"{i:010d}{ext}", folder / f"{i:010d}{ext}")
    return date


# -- the stereo check on a synthetic pair ----------------------------------------------------


H, W = 120, 320
D_BG, D_FG = 10, 40  # disparities, pixels: a wall at 38.4 m, a board at 9.6 m
BOARD = (30, 90, 150, 230)  # rows y0:y1, columns x0:x1 of the board in the left image


def _texture(seed: int) -> np.ndarray:
    import cv2

    r = np.random.default_rng(seed).random((H, W + 100)).astype(np.float32)
    r = cv2.GaussianBlur(r, (0, 0), 1.2)
    return ((r - r.min()) / (r.max() - r.min()) * 255).astype(np.uint8)


def _pair():
    """A textured wall (disparity 10) with a textured board in front (disparity 40): the
    right image is rendered by shifting each layer by its disparity, the board on top."""
    wall, board = _texture(1), _texture(2)
    y0, y1, x0, x1 = BOARD
    cols = np.arange(W)
    left = wall[:, cols].copy()
    left[y0:y1, x0:x1] = board[y0:y1, x0:x1]
    right = wall[:, cols + D_BG].copy()
    src = cols + D_FG  # the left column a right pixel of the board shows
    on = (src >= x0) & (src < x1)
    right[y0:y1, on] = board[y0:y1, src[on]]
    truth = np.full((H, W), float(D_BG))
    truth[y0:y1, x0:x1] = D_FG
    return left, right, truth


def test_sgbm_finds_the_rendered_disparity():
    from sparsetools.ops.stereo import sgbm_disparity

    left, right, truth = _pair()
    disp = sgbm_disparity(left, right)
    assert disp.dtype == np.float32 and disp.shape == (H, W)
    # no match is possible in the left num_disparities (128) columns
    assert np.isnan(disp[:, :100]).all()
    y0, y1, x0, x1 = BOARD
    inner = np.zeros((H, W), bool)
    inner[y0 + 4 : y1 - 4, x0 + 4 : x1 - 4] = True  # the board away from its edges
    wall = np.zeros((H, W), bool)
    wall[4:-4, 140:] = True
    wall[y0 - 8 : y1 + 8, x0 - 8 : x1 + 8] = False
    for region in (inner, wall):
        d = disp[region]
        assert np.isfinite(d).mean() > 0.95
        # within 1 px nearly everywhere (SGBM leaves a few speckles near the board's edges)
        assert np.mean(np.abs(d - truth[region]) <= 1.0) > 0.98


def test_the_stereo_check_drops_the_wrong_points_and_keeps_the_right_ones():
    from sparsetools.ops.stereo import StereoCheckSettings, stereo_check

    left, right, truth = _pair()
    rng = np.random.default_rng(0)
    y0, y1, x0, x1 = BOARD
    depth = np.zeros((H, W), np.float32)
    # right points: on the board and on the wall, away from the board's edges
    board_px = list(zip(rng.integers(y0 + 8, y1 - 8, 60).tolist(),
                        rng.integers(x0 + 8, x1 - 8, 60).tolist(), strict=True))  # fmt: skip
    wall_px = list(zip(rng.integers(5, 25, 40).tolist(), rng.integers(140, 315, 40).tolist(),
                       strict=True))  # fmt: skip
    right_px = set(board_px + wall_px)
    for v, u in right_px:
        depth[v, u] = FX * BASELINE / truth[v, u]
    # wrong points: see-through (the wall's depth on the board), a phantom in front of the
    # wall, a depth off by 20 % (8 px at disparity 40)
    wrong = {(45, 170): FX * BASELINE / D_BG, (60, 200): FX * BASELINE / D_BG,
             (100, 250): FX * BASELINE / 25.0, (10, 290): FX * BASELINE / 4.0,
             (50, 180): FX * BASELINE / D_FG * 1.25}  # fmt: skip
    for (v, u), z in wrong.items():
        depth[v, u] = z
    # inside the margin: 2 px off at disparity 40 (< 3 px): kept
    near_px = (70, 210)
    depth[near_px] = FX * BASELINE / (D_FG - 2)
    # where SGBM has no disparity (left border), even a wrong point is kept: no opinion
    blind = (60, 20)
    depth[blind] = 3.0
    filtered, removed, disp = stereo_check(depth, left, right, fx=FX, baseline=BASELINE)
    assert pixels(removed) == set(wrong)
    assert np.all(filtered[removed] == 0)
    kept = ~removed & (depth > 0)
    assert np.array_equal(filtered[kept], depth[kept])
    assert np.isnan(disp[blind]) and filtered[blind] == 3.0
    assert filtered[near_px] > 0
    # the margin, written out: more than 3 px AND more than 5 % of the point's disparity
    d_lidar = FX * BASELINE / depth[depth > 0]
    err = np.abs(d_lidar - disp[depth > 0])
    expect = np.isfinite(err) & (err > 3.0) & (err > 0.05 * d_lidar)
    assert np.array_equal(removed[depth > 0], expect)
    # a 10 px margin keeps the points 8 px (the 20 % one) and 6 px off, drops 15 and 30 px
    loose = stereo_check(depth, left, right, fx=FX, baseline=BASELINE,
                         settings=StereoCheckSettings(abs_px=10.0))[1]  # fmt: skip
    assert pixels(loose) == set(wrong) - {(50, 180), (10, 290)}
    # an empty map stays empty
    empty = stereo_check(np.zeros((H, W), np.float32), left, right, fx=FX, baseline=BASELINE)
    assert not empty[0].any() and not empty[1].any()


def test_stereo_settings_and_shapes_are_checked():
    from sparsetools.errors import ParameterError
    from sparsetools.ops.stereo import SgbmSettings, stereo_check

    with pytest.raises(ParameterError, match="multiple of 16"):
        SgbmSettings(num_disparities=100)
    with pytest.raises(ParameterError, match="odd"):
        SgbmSettings(block_size=4)
    left, right, _ = _pair()
    with pytest.raises(ParameterError):
        stereo_check(np.zeros((10, 10), np.float32), left, right, fx=FX, baseline=BASELINE)
    with pytest.raises(ParameterError):
        stereo_check(np.zeros((H, W), np.float32), left, right[:, :-1], fx=FX, baseline=BASELINE)


def test_the_stereo_rig_of_the_kitti_calibration(tmp_path):
    from sparsetools.errors import CalibrationError
    from sparsetools.io.calib import read_kitti_stereo_rig

    p2 = "7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0 7.215377e+02 1.728540e+02 " \
         "2.163791e-01 0 0 1 2.745884e-03"  # fmt: skip
    p3 = "7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0 7.215377e+02 1.728540e+02 " \
         "2.199936e+00 0 0 1 2.729905e-03"  # fmt: skip
    (tmp_path / "calib_cam_to_cam.txt").write_text(f"P_rect_02: {p2}\nP_rect_03: {p3}\n")
    fx, b = read_kitti_stereo_rig(tmp_path)
    assert fx == pytest.approx(721.5377)
    assert b == pytest.approx((44.85728 + 339.5242) / 721.5377)
    (tmp_path / "calib_cam_to_cam.txt").write_text(f"P_rect_02: {p3}\nP_rect_03: {p2}\n")
    with pytest.raises(CalibrationError, match="not to the right"):
        read_kitti_stereo_rig(tmp_path)


# -- KITTI raw routes on the real sequence -----------------------------------------------------


@pytest.fixture(scope="module")
def raw(real_dir, tmp_path_factory):
    return _raw_tree(real_dir, tmp_path_factory.mktemp("raw"), FRAMES)


@pytest.fixture(scope="module")
def scan_ds(raw, tmp_path_factory):
    ds = tmp_path_factory.mktemp("scan") / "ds"
    return ds, summary("dataset", "kitti-raw", raw, "-o", ds, "--beams", "4")


@pytest.fixture(scope="module")
def acc_ds(raw, tmp_path_factory):
    ds = tmp_path_factory.mktemp("acc") / "ds"
    s = summary("dataset", "kitti-raw", raw, "-o", ds, "--beams", "4", "--gt-method",
                "accumulated", "--gt-neighbours", "2", "--icp-min-range", "20")  # fmt: skip
    return ds, s


@pytest.mark.real
def test_gt_scan_is_the_projected_scan_byte_for_byte(raw, scan_ds, tmp_path):
    """The default is today's route: the ground truth files are ``project``'s maps, byte for
    byte, the input the 4-beam maps, and ``--gt-method scan`` is the same build."""
    ds, s = scan_ds
    assert s["samples"] == len(FRAMES) and s["gt"]["method"] == "scan"
    proj = tmp_path / "proj"
    assert run("project", raw, "-o", proj).exit_code == 0
    for r in rows(ds):
        frame = r["id"].split("/")[-1]
        assert (ds / r["gt_path"]).read_bytes() == (proj / DRIVE / f"{frame}.png").read_bytes()
    # rows as 0.2 wrote them (no gt_method: tests/test_compat_v020.py), read as "scan"
    assert all("sample" not in json.loads(r["generation_params"]) for r in rows(ds))
    assert "gt methods                         scan (5)" in run("dataset", "info", ds).output
    same = tmp_path / "same"
    summary("dataset", "kitti-raw", raw, "-o", same, "--beams", "4", "--gt-method", "scan")
    # every file but the records and the stages' calibration JSONs (they name their paths)
    files = sorted(p for p in ds.rglob("*") if p.is_file() and ".sparsetools" not in p.parts
                   and p.suffix != ".json")  # fmt: skip
    assert {p.suffix for p in files} == {".png", ".bin", ".parquet"}
    for a in files:
        b = same / a.relative_to(ds)
        assert a.read_bytes() == b.read_bytes(), a.relative_to(ds)
    # the record holds no new setting: a dataset of an earlier version resumes
    params = json.loads(rows(ds)[0]["generation_params"])["params"]
    assert params == {"route": "kitti-raw", "beams": 4}


@pytest.mark.real
def test_filter_occluded_gt_is_a_subset_of_the_scan_gt(raw, scan_ds, tmp_path):
    ds = tmp_path / "occ"
    s = summary("dataset", "kitti-raw", raw, "-o", ds, "--beams", "4", "--filter-occluded")
    assert s["gt"]["method"] == "scan+occlusion" and s["gt"]["occluded_pixels"] > 0
    scan, occ = gt_maps(scan_ds[0]), gt_maps(ds)
    assert scan.keys() == occ.keys()
    removed = 0
    for k, m in occ.items():
        assert np.array_equal(m[m > 0], scan[k][m > 0])  # every value kept is the scan's
        removed += int(np.count_nonzero(scan[k] > 0) - np.count_nonzero(m > 0))
    assert removed == s["gt"]["occluded_pixels"]
    assert 0 < removed < 0.2 * sum(np.count_nonzero(m) for m in scan.values())
    assert {p["gt_method"] for p in sample_params(ds).values()} == {"scan+occlusion"}
    # the input is the unfiltered scan's 4 beams: the same as the scan route's
    a, b = rows(scan_ds[0]), rows(ds)
    assert [r["sparse_sha256"] for r in a] == [r["sparse_sha256"] for r in b]


@pytest.mark.real
def test_accumulated_gt_is_denser_and_keeps_frame_ts_own_values(scan_ds, acc_ds):
    ds, s = acc_ds
    g = s["gt"]
    assert g["method"] == "accumulated" and g["pose_source"] == "icp"
    assert g["stereo_checked"] == 0 and g["clipped_windows"] == 4  # 5 frames, K = 2
    assert g["icp"]["pairs"] == len(FRAMES) - 1 and g["icp"]["fitness_min"] > 0.85
    scan, acc = gt_maps(scan_ds[0]), gt_maps(ds)
    params = sample_params(ds)
    n = len(FRAMES)
    for i, (k, a) in enumerate(sorted(acc.items())):
        own = scan[k]
        # denser than the single scan (KITTI's recipe: about 4x with 11 scans)
        assert np.count_nonzero(a) > 1.8 * np.count_nonzero(own), k
        both = (a > 0) & (own > 0)
        # z-buffer rule: a pixel frame t measured holds its value or a nearer one (nearest
        # wins). The exception: frame t's nearest point there was occluded while a farther
        # one, whose window is smaller, was not (4 of 63,617 pixels here).
        assert np.mean(a[both] > own[both]) < 1e-3, k
        assert np.mean(a[both] == own[both]) > 0.8, k
        lo, hi = min(i, 2), min(n - 1 - i, 2)
        assert params[k] == {
            "gt_method": "accumulated(t-2..t+2,poses=icp,occlusion,consistency)",
            "gt_window": f"t-{lo}..t+{hi}",
        }
    info = run("dataset", "info", ds)
    assert "gt methods" in info.output
    assert "accumulated(t-2..t+2,poses=icp,occlusion,consistency) (5)" in info.output


@pytest.mark.real
def test_accumulated_rerun_and_refusals(raw, acc_ds):
    ds, _ = acc_ds
    args = ["dataset", "kitti-raw", raw, "-o", ds, "--beams", "4", "--gt-method", "accumulated",
            "--icp-min-range", "20"]  # fmt: skip
    again = summary(*args, "--gt-neighbours", "2")
    assert again["processed"] == 0 and again["skipped_existing"] == len(FRAMES)
    r = run(*args, "--gt-neighbours", "3")
    assert r.exit_code != 0 and "--gt-neighbours" in r.output and "Traceback" not in r.output


@pytest.mark.real
def test_stereo_check_in_the_route_with_a_synthetic_image_03(real_dir, tmp_path):
    """image_03 made from image_02 shifted by 20 px: stereo sees one plane at fx B / 20 =
    19.2 m, so the check keeps exactly the points within the margin of it (or where SGBM has
    no disparity), and the rows say ',stereo'."""
    import cv2

    from sparsetools.ops.stereo import sgbm_disparity

    date = _raw_tree(real_dir, tmp_path / "raw", range(4, 7))
    shift = 20
    for p in sorted((date / DRIVE / "image_02" / "data").glob("*.png")):
        img = cv2.imread(str(p))
        right = np.zeros_like(img)
        right[:, : img.shape[1] - shift] = img[:, shift:]
        out = date / DRIVE / "image_03" / "data" / p.name
        out.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out), right)
    ds = tmp_path / "ds"
    s = summary("dataset", "kitti-raw", date, "-o", ds, "--beams", "4", "--gt-method",
                "accumulated", "--gt-neighbours", "1", "--icp-min-range", "20")  # fmt: skip
    assert s["gt"]["stereo_checked"] == 3 and s["gt"]["stereo_removed"] > 0
    from sparsetools.io.image import read_depth_png

    acc_dir = ds / ".sources" / "gt_accumulated" / DRIVE
    params = sample_params(ds)
    for k, checked in gt_maps(ds).items():
        frame = k.split("/")[-1]
        assert params[k]["gt_method"].endswith(",stereo)")
        before = read_depth_png(acc_dir / f"{frame}.png")
        left = cv2.imread(str(date / DRIVE / "image_02" / "data" / f"{frame}.png"))
        disp = sgbm_disparity(left, cv2.imread(str(date / DRIVE / "image_03" / "data" /
                                                   f"{frame}.png")))  # fmt: skip
        z = before[before > 0].astype(np.float64)
        d = FX * BASELINE / z
        err = np.abs(d - disp[before > 0])
        keep = ~(np.isfinite(err) & (err > 3.0) & (err > 0.05 * d))
        assert np.array_equal(checked[before > 0] > 0, keep)
        assert np.array_equal(checked[checked > 0], before[checked > 0])


@pytest.mark.real
def test_oxts_poses_when_the_drive_has_them_and_the_maps_of_accumulate(real_dir, tmp_path):
    """A drive with oxts packets (written here: 0.22 m north per frame, heading north): the
    route takes the oxts poses (no ICP stage) and its ground truth is, byte for byte, what
    ``sparsetools accumulate --filter-occluded`` makes of the same drive."""
    date = _raw_tree(real_dir, tmp_path / "raw", range(4, 7))
    oxts = date / DRIVE / "oxts" / "data"
    oxts.mkdir(parents=True)
    for i in range(4, 7):
        packet = (
            [49.011 + 2e-6 * i, 8.43, 112.0, 0.0, 0.0, np.pi / 2] + [0.0] * 19 + [4, 11, 6, 6, 6]
        )
        (oxts / f"{i:010d}.txt").write_text(" ".join(map(repr, packet)) + "\n")
    ds = tmp_path / "ds"
    s = summary("dataset", "kitti-raw", date, "-o", ds, "--gt-method", "accumulated",
                "--gt-neighbours", "1")  # fmt: skip
    assert s["gt"]["pose_source"] == "oxts" and "icp" not in s["gt"]
    assert not (ds / ".sources" / "gt_accumulated" / "icp").exists()
    assert {p["gt_method"] for p in sample_params(ds).values()} == {
        "accumulated(t-1..t+1,poses=oxts,occlusion,consistency)"
    }
    acc = tmp_path / "acc"
    assert (
        run("accumulate", date, "-o", acc, "--neighbours", "1", "--filter-occluded").exit_code == 0
    )
    for r in rows(ds):
        frame = r["id"].split("/")[-1]
        assert (ds / r["gt_path"]).read_bytes() == (acc / DRIVE / f"{frame}.png").read_bytes()


@pytest.mark.real
@pytest.mark.parametrize(
    ("extra", "match"),
    [
        (["--gt-neighbours", "3"], "--gt-neighbours goes with --gt-method accumulated"),
        (["--stereo-check"], "--stereo-check/--no-stereo-check goes with --gt-method accumulated"),
        (["--icp-min-range", "20"], "--icp-min-range goes with --gt-method accumulated"),
        (["--gt-method", "accumulated", "--stereo-check"], "has no image_03"),
        (["--gt-method", "stereo"], "Invalid value for '--gt-method'"),
    ],
)
def test_gt_usage_errors_are_one_line(raw, tmp_path, extra, match):
    r = run("dataset", "kitti-raw", raw, "-o", tmp_path / "ds", *extra)
    assert r.exit_code != 0
    lines = [ln for ln in r.output.splitlines() if ln.startswith("Error")]
    assert len(lines) == 1 and match in lines[0], r.output
    assert "Traceback" not in r.output
    assert not (tmp_path / "ds" / "manifest.parquet").exists()


# -- nuScenes ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def nus(real_dir, tmp_path_factory):
    from _nuscenes_tree import build_tree

    root = tmp_path_factory.mktemp("nuscenes")
    build_tree(real_dir, root)
    return root


@pytest.mark.real
def test_nuscenes_gt_sweeps_with_filter_occluded(nus, tmp_path):
    base = ["dataset", "nuscenes", nus, "--sweeps", "1", "--gt-sweeps", "3"]
    plain = summary(*base, "-o", tmp_path / "plain")
    occ = summary(*base, "--filter-occluded", "-o", tmp_path / "occ")
    assert plain["gt"]["methods"] == {"sweeps(1)": 1}  # the tree holds one LIDAR_TOP sweep
    assert occ["gt"]["methods"] == {"sweeps(1)+occlusion": 1}
    (k, a), (k2, b) = (
        next(iter(gt_maps(tmp_path / "plain").items())),
        next(iter(gt_maps(tmp_path / "occ").items())),
    )
    assert k == k2
    assert np.array_equal(b[b > 0], a[b > 0])  # a subset of the unfiltered ground truth
    removed = int(np.count_nonzero(a) - np.count_nonzero(b))
    assert removed == occ["gt"]["occluded_pixels"] > 0
    (p,) = sample_params(tmp_path / "occ").values()
    assert p == {"sweeps_merged": 1, "gt_sweeps_merged": 1, "gt_method": "sweeps(1)+occlusion"}
    info = run("dataset", "info", tmp_path / "occ").output
    assert "gt methods" in info and "sweeps(1)+occlusion (1)" in info
    # the input (radar) is the same in both
    assert (
        rows(tmp_path / "plain")[0]["sparse_sha256"] == rows(tmp_path / "occ")[0]["sparse_sha256"]
    )
    r = run(*base, "--filter-occluded", "--gt-sensor", "none", "-o", tmp_path / "none")
    assert r.exit_code != 0 and "not with --gt-sensor none" in r.output
    assert "Traceback" not in r.output
