"""An exact output size: ``Calibration.resized_to`` and ``dataset kitti-raw --resize-to WxH``
(monodepth2's 640x192 KITTI setting), on the real KITTI sequence.

The references are written here from KITTI's own calibration text: the continuous pixel of a
point at the native size, then the per-axis map of pixel centres ``u' = sx (u + 0.5) - 0.5``.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from _cli import run, summary
from _kitti_raw_tree import make_raw_tree
from sparsetools.calibration import Calibration
from sparsetools.errors import ParameterError

DATE = "2011_09_26"
DRIVE = f"{DATE}_drive_0001_sync"
N = 3  # frames
W0, H0 = 1242, 375  # the sequence's images
SIZE = (640, 192)


# -- Calibration.resized_to ------------------------------------------------------------------


def _calib(width=W0, height=H0, P=None) -> Calibration:
    K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 0.3)
    return Calibration(K=K, T_cam_from_sensor=T, width=width, height=height, P=P)


def test_resized_to_scales_each_axis_by_its_own_factor():
    c = _calib().resized_to(640, 192)
    sx, sy = 640 / 1242, 192 / 375
    expected = np.array(
        [
            [721.5377 * sx, 0.0, (609.5593 + 0.5) * sx - 0.5],
            [0.0, 721.5377 * sy, (172.854 + 0.5) * sy - 0.5],
            [0.0, 0.0, 1.0],
        ]
    )
    np.testing.assert_allclose(c.K, expected, rtol=0, atol=1e-12)
    assert c.size == (640, 192)
    assert c.fx != c.fy  # the aspect ratio changed (1242/375 -> 640/192)
    # the transform to the camera does not change
    np.testing.assert_array_equal(c.T_cam_from_sensor, _calib().T_cam_from_sensor)


def test_resized_to_scales_a_kitti_P_and_its_translation_column():
    P = np.array([[721.5377, 0, 609.5593, 44.85728], [0, 721.5377, 172.854, 0.2163791],
                  [0, 0, 1, 0.002745884]])  # fmt: skip
    c = _calib(P=P).resized_to(640, 192)
    sx, sy = 640 / 1242, 192 / 375
    # row 0 of P' is sx * row 0 + (sx/2 - 1/2) * row 2 (and so for row 1 with sy)
    np.testing.assert_allclose(c.P[0], sx * P[0] + (sx / 2 - 0.5) * P[2], atol=1e-12)
    np.testing.assert_allclose(c.P[1], sy * P[1] + (sy / 2 - 0.5) * P[2], atol=1e-12)
    np.testing.assert_array_equal(c.P[2], P[2])


def test_a_point_lands_at_the_scaled_pixel_of_the_old_one():
    old = _calib()
    new = old.resized_to(640, 192)
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-20, 20, 50), rng.uniform(-3, 3, 50), rng.uniform(2, 80, 50),
                np.ones(50)]  # fmt: skip

    def pixels(c):
        h = pts @ c.projection.T
        return h[:, 0] / h[:, 2], h[:, 1] / h[:, 2], h[:, 2]

    u0, v0, z0 = pixels(old)
    u1, v1, z1 = pixels(new)
    sx, sy = 640 / 1242, 192 / 375
    np.testing.assert_allclose(u1, sx * (u0 + 0.5) - 0.5, rtol=0, atol=1e-9)
    np.testing.assert_allclose(v1, sy * (v0 + 0.5) - 0.5, rtol=0, atol=1e-9)
    np.testing.assert_allclose(z1, z0, rtol=0, atol=1e-12)  # depth is untouched
    # the image's corners (pixel edges) map to the new image's corners
    assert sx * (-0.5 + 0.5) - 0.5 == -0.5 and sx * (W0 - 0.5 + 0.5) - 0.5 == pytest.approx(639.5)


@pytest.mark.parametrize(("width", "height", "scale"),
                         [(1242, 376, 0.5), (1242, 375, 2 / 3), (1242, 375, 2.0)])  # fmt: skip
def test_resized_to_an_exact_scale_agrees_with_resized(width, height, scale):
    P = np.array([[721.5377, 0, 609.5593, 44.85728], [0, 721.5377, 172.854, 0.2163791],
                  [0, 0, 1, 0.002745884]])  # fmt: skip
    c = _calib(width=width, height=height, P=P)
    w, h = round(width * scale), round(height * scale)
    assert w == pytest.approx(width * scale) and h == pytest.approx(height * scale)
    a, b = c.resized_to(w, h), c.resized(scale)
    assert a.size == b.size == (w, h)
    np.testing.assert_allclose(a.K, b.K, rtol=0, atol=1e-12)
    np.testing.assert_allclose(a.P, b.P, rtol=0, atol=1e-12)


def test_resized_to_the_same_size_changes_nothing():
    c = _calib()
    np.testing.assert_array_equal(c.resized_to(W0, H0).K, c.K)


@pytest.mark.parametrize("size", [(0, 192), (640, -1), (640.5, 192), (True, 192)])
def test_resized_to_refuses_a_size_that_is_not_two_positive_integers(size):
    with pytest.raises(ParameterError, match="positive integer"):
        _calib().resized_to(*size)


def test_resized_to_needs_the_calibration_size():
    with pytest.raises(ParameterError, match="image size unknown"):
        _calib(width=None, height=None).resized_to(640, 192)


@pytest.mark.parametrize("kind", ["project", "images", "accumulate"])
def test_resize_to_is_recorded_only_when_set_and_excludes_resize(kind):
    from sparsetools.pipeline.accumulate import AccumulateRunSettings
    from sparsetools.pipeline.camera_images import CameraImageSettings
    from sparsetools.pipeline.project import ProjectSettings
    from sparsetools.pipeline.provenance import settings_dict

    cls = {"project": ProjectSettings, "images": CameraImageSettings,
           "accumulate": AccumulateRunSettings}[kind]  # fmt: skip
    # folders made before the option resume: their records have no resize_to
    assert "resize_to" not in settings_dict(cls())
    assert settings_dict(cls(resize_to="640x192"))["resize_to"] == [640, 192]
    with pytest.raises(ParameterError, match="--resize-to"):
        cls(resize_to="640x0")
    if kind != "accumulate":
        with pytest.raises(ParameterError, match="exclude each other"):
            cls(resize=0.5, resize_to=(640, 192))


# -- dataset kitti-raw --resize-to -----------------------------------------------------------


def _values(path: Path) -> dict[str, np.ndarray]:
    """``KEY: v v v`` lines of a KITTI calibration text file."""
    out = {}
    for line in path.read_text().splitlines():
        key, _, rest = line.partition(":")
        try:
            out[key] = np.array([float(v) for v in rest.split()])
        except ValueError:
            continue  # calib_time
    return out


@pytest.fixture(scope="module")
def raw_root(real_dir, tmp_path_factory):
    """raw/2011_09_26/{calib pair, drive_0001 frames 0-2 (image_02, velodyne_points)}."""
    return make_raw_tree(real_dir, tmp_path_factory.mktemp("raw"), {DRIVE: range(N)})


@pytest.fixture(scope="module")
def built(raw_root, tmp_path_factory):
    ds = tmp_path_factory.mktemp("resize") / "ds"
    args = ["dataset", "kitti-raw", raw_root, "-o", ds, "--beams", "4",
            "--resize-to", f"{SIZE[0]}x{SIZE[1]}"]  # fmt: skip
    return ds, args, summary(*args)


def _reference_map(cloud: Path, cam: dict, velo: dict, size) -> np.ndarray:
    """The sparse map of a scan at ``size``, from KITTI's text: P_rect_02 R_rect_00 [R|T] at
    the native size, then each pixel mapped to the resized grid; the nearest point wins."""
    pts = np.fromfile(cloud, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    Rv, Tv = velo["R"].reshape(3, 3), velo["T"]
    R0 = cam["R_rect_00"].reshape(3, 3)
    P2 = cam["P_rect_02"].reshape(3, 4)
    cam_pts = (pts @ Rv.T + Tv) @ R0.T  # rectified camera 0 frame
    h = cam_pts @ P2[:, :3].T + P2[:, 3]
    z = h[:, 2]
    front = z > 0.1  # the default --min-depth
    u0, v0, z = h[front, 0] / z[front], h[front, 1] / z[front], z[front]
    sx, sy = size[0] / W0, size[1] / H0
    u = np.rint(sx * (u0 + 0.5) - 0.5)
    v = np.rint(sy * (v0 + 0.5) - 0.5)
    inside = (u >= 0) & (u < size[0]) & (v >= 0) & (v < size[1])
    u, v, z = u[inside].astype(int), v[inside].astype(int), z[inside].astype(np.float32)
    flat = v * size[0] + u
    order = np.lexsort((z, flat))  # by pixel, nearest first
    first = np.unique(flat[order], return_index=True)[1]
    out = np.zeros(size[0] * size[1], np.float32)
    out[flat[order][first]] = z[order][first]
    return out.reshape(size[1], size[0])


@pytest.mark.real
def test_resize_to_gives_images_maps_and_intrinsics_at_that_size(raw_root, built):
    from sparsetools.io.dataset_reader import DatasetReader

    ds, _, s = built
    assert s["samples"] == N and s["failed"] == 0
    reader = DatasetReader(ds)
    rows = {r["id"]: r for r in reader.manifest.to_pylist()}
    assert sorted(rows) == [f"{DRIVE}/{i:010d}" for i in range(N)]
    cam = _values(raw_root / DATE / "calib_cam_to_cam.txt")
    velo = _values(raw_root / DATE / "calib_velo_to_cam.txt")
    P2 = cam["P_rect_02"].reshape(3, 4)
    sx, sy = SIZE[0] / W0, SIZE[1] / H0
    K = np.array([[P2[0, 0] * sx, 0, (P2[0, 2] + 0.5) * sx - 0.5],
                  [0, P2[1, 1] * sy, (P2[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])  # fmt: skip
    for sid, row in rows.items():
        assert (row["width"], row["height"]) == SIZE
        assert json.loads(row["generation_params"])["params"]["resize_to"] == list(SIZE)
        for name, value in (("fx", K[0, 0]), ("fy", K[1, 1]), ("cx", K[0, 2]), ("cy", K[1, 2])):
            assert row[name] == pytest.approx(value, abs=1e-9), name
        sample = reader.sample(sid)
        np.testing.assert_allclose(sample["intrinsics"], K, atol=1e-9)
        assert sample["rgb"].shape == (SIZE[1], SIZE[0], 3)
        assert sample["sparse"].shape == sample["gt"].shape == (SIZE[1], SIZE[0])
        # the image: the native one shrunk by area interpolation
        frame = sid.split("/")[1]
        native = cv2.imread(str(raw_root / DATE / DRIVE / "image_02" / "data" / f"{frame}.png"))
        assert native.shape[:2] == (H0, W0)
        expected_rgb = cv2.cvtColor(cv2.resize(native, SIZE, interpolation=cv2.INTER_AREA),
                                    cv2.COLOR_BGR2RGB)  # fmt: skip
        np.testing.assert_array_equal(sample["rgb"], expected_rgb)
        # the maps: the scans projected at 640x192 by the reference, pixel for pixel (PNG
        # depth is quantised to 1/256 m)
        for key, cloud in (
            ("sparse", ds / ".sources" / "beams4" / DRIVE / f"{frame}.bin"),
            ("gt", raw_root / DATE / DRIVE / "velodyne_points" / "data" / f"{frame}.bin"),
        ):
            ref = _reference_map(cloud, cam, velo, SIZE)
            got = sample[key]
            assert np.array_equal(got > 0, ref > 0), key
            assert np.count_nonzero(ref) > (100 if key == "sparse" else 5000)
            np.testing.assert_allclose(got[ref > 0], ref[ref > 0], rtol=0, atol=0.5 / 256 + 1e-6)
        assert 0 < row["n_sparse"] < row["n_gt"]


@pytest.mark.real
def test_a_rerun_is_a_no_op_and_another_size_is_refused(built):
    ds, args, _ = built
    again = summary(*args)
    assert again["processed"] == 0 and again["skipped_existing"] == N
    manifest = (ds / "manifest.parquet").read_bytes()
    for other in (["--resize-to", "320x96"], []):
        r = run(*args[:-2], *other)
        assert r.exit_code != 0
        lines = r.output.strip().splitlines()
        assert len(lines) == 1 and "--resize-to" in lines[0], r.output
        assert "Traceback" not in r.output
    assert (ds / "manifest.parquet").read_bytes() == manifest


@pytest.mark.real
@pytest.mark.parametrize("value", ["0x0", "640", "640x-1", "640x192.5", "axb"])
def test_bad_sizes_are_one_line_usage_errors(raw_root, tmp_path, value):
    out = tmp_path / "ds"
    r = run("dataset", "kitti-raw", raw_root, "-o", out, "--resize-to", value)
    assert r.exit_code == 2
    errors = [ln for ln in r.output.splitlines() if ln.startswith("Error")]
    assert len(errors) == 1 and "--resize-to" in errors[0], r.output
    assert not out.exists()


@pytest.mark.real
def test_accumulated_ground_truth_is_made_at_the_new_size(raw_root, tmp_path):
    """K = 0: frame t's own scan, occlusion-filtered, at 640x192: every point it keeps sits
    where the reference puts it, with its depth; the calibration is the scaled one."""
    from sparsetools.io.dataset_reader import DatasetReader

    ds = tmp_path / "ds"
    args = ["dataset", "kitti-raw", raw_root, "-o", ds, "--resize-to", "640x192",
            "--gt-method", "accumulated", "--gt-neighbours", "0"]  # fmt: skip
    s = summary(*args)
    assert s["samples"] == N and s["gt"]["method"] == "accumulated"
    cam = _values(raw_root / DATE / "calib_cam_to_cam.txt")
    velo = _values(raw_root / DATE / "calib_velo_to_cam.txt")
    reader = DatasetReader(ds)
    for row in reader.manifest.to_pylist():
        assert (row["width"], row["height"]) == SIZE
        assert row["fx"] == pytest.approx(cam["P_rect_02"][0] * SIZE[0] / W0, abs=1e-9)
        frame = row["frame"]
        gt = reader.sample(row["id"])["gt"]
        assert gt.shape == (SIZE[1], SIZE[0])
        ref = _reference_map(raw_root / DATE / DRIVE / "velodyne_points" / "data" /
                             f"{frame}.bin", cam, velo, SIZE)  # fmt: skip
        kept = gt > 0
        assert not np.any(kept & (ref == 0))  # no point where the reference has none
        np.testing.assert_allclose(gt[kept], ref[kept], rtol=0, atol=0.5 / 256 + 1e-6)
        # the occlusion test removes a minority of the pixels
        assert 0.5 * np.count_nonzero(ref) < np.count_nonzero(kept) <= np.count_nonzero(ref)
        calib = json.loads((ds / ".sources" / "gt_accumulated" / "calib" / DRIVE /
                            f"{frame}.json").read_text())  # fmt: skip
        assert calib["resize_to"] == list(SIZE) and (calib["width"], calib["height"]) == SIZE
    assert summary(*args)["processed"] == 0
    # another size is refused by the accumulate stage's record, before anything is written
    r = run(*args[:-5], "320x96", *args[-4:])
    assert r.exit_code != 0 and "--resize-to" in r.output and "Traceback" not in r.output
    image = cv2.imread(str(ds / ".sources" / "images" / DRIVE / "0000000000.png"))
    assert image.shape[:2] == (SIZE[1], SIZE[0])


@pytest.mark.real
def test_stereo_check_at_the_new_size_scales_fx(raw_root, tmp_path):
    """A textured pair shifted by 40 native pixels (so 40 * 640/1242 resized ones): points at
    the pair's depth are kept, points at twice it (half the disparity) are removed; with fx
    left unscaled every point would disagree."""
    from sparsetools.io.image import read_depth_png, write_depth_png
    from sparsetools.io.sources import Frame, FrameKey
    from sparsetools.pipeline.core import run_job
    from sparsetools.pipeline.stereo_check import StereoCheckJob

    rng = np.random.default_rng(1)
    texture = cv2.resize(rng.integers(0, 256, (H0 // 3, W0 // 3 + 20), dtype=np.uint8),
                         (W0 + 60, H0), interpolation=cv2.INTER_LINEAR)  # fmt: skip
    d = 40
    left, right = texture[:, :W0], texture[:, d : d + W0]  # right(u) = left(u + d)
    left_p, right_p = tmp_path / "l.png", tmp_path / "r.png"
    cv2.imwrite(str(left_p), cv2.merge([left] * 3))
    cv2.imwrite(str(right_p), cv2.merge([right] * 3))
    cam = _values(raw_root / DATE / "calib_cam_to_cam.txt")
    fx = cam["P_rect_02"][0]
    baseline = (cam["P_rect_02"][3] - cam["P_rect_03"][3]) / fx
    z = fx * baseline / d  # the pair's depth: disparity d at the native size
    depth = np.zeros((SIZE[1], SIZE[0]), np.float32)
    depth[60:130:4, 200:400:4] = z  # kept
    depth[62:130:4, 200:400:4] = 2 * z  # half the disparity: removed
    maps = tmp_path / "maps"
    key = FrameKey("seq", "0")
    write_depth_png(key.path(maps, ".png"), depth)
    frame = Frame(key=key, depth=key.path(maps, ".png"), image=left_p, calib=raw_root / DATE)
    job = StereoCheckJob(right=((str(key), str(right_p)),), resize_to=SIZE)
    s = run_job(job, [frame], tmp_path / "out")
    assert s.totals["checked"] == 1
    out = read_depth_png(key.path(tmp_path / "out", ".png"))
    near, far = depth == np.float32(z), depth == np.float32(2 * z)
    assert np.count_nonzero(out[near]) >= 0.95 * np.count_nonzero(near)
    assert np.count_nonzero(out[far]) <= 0.05 * np.count_nonzero(far)


@pytest.mark.real
def test_stored_points_reproject_to_the_resized_maps(raw_root, tmp_path):
    from sparsetools.io.dataset_reader import DatasetReader
    from sparsetools.train.transforms import reproject

    out = tmp_path / "pts"
    summary("dataset", "kitti-raw", raw_root, "-o", out, "--beams", 64, "--resize-to", "640x192",
            "--store-points")  # fmt: skip
    ds = DatasetReader(out)
    assert len(ds) > 0
    for i in range(len(ds)):
        xyz, _ring = ds.points(i)
        depth = reproject(xyz, ds.geometry(i)["intrinsics"], 192, 640)
        stored = ds.sample(i)["sparse"]
        assert stored.shape == (192, 640) and (stored > 0).sum() > 1000
        # the stored PNG holds depth in 1/256 m steps
        np.testing.assert_array_equal(np.round(depth * 256) / 256, stored)


def test_resize_to_with_several_cameras_is_refused(raw_root, tmp_path):
    r = run("dataset", "kitti-raw", raw_root, "-o", tmp_path / "rig", "--resize-to", "640x192",
            "--cameras", "image_02,image_03")  # fmt: skip
    assert r.exit_code == 2 and "several --cameras" in r.output
    assert not (tmp_path / "rig" / "manifest.parquet").exists()
