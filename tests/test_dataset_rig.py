"""Every camera of a rig, each sample's geometry, loading with torch (issue 26).

A 2-camera KITTI raw dataset (image_03 a copy of image_02 of the real sequence, with the
real calibration's P_rect_03) and a 6-camera nuScenes dataset (the v1.0-mini-style tree of
tests/_nuscenes_tree.py with the demo's six real images): every camera kept, ids unique,
splits that keep a frame's cameras together, geometry columns equal to matrices computed here
from the calibration files, and the reader / torch Dataset on them.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.dataset import MANIFEST_SCHEMA, OPTIONAL_SCHEMA, REFERENCE_COLUMNS
from sparsetools.io.dataset_reader import DatasetReader

sys.path.insert(0, str(Path(__file__).parent))
from _kitti_raw_tree import make_raw_tree
from _nuscenes_tree import CAMERAS, build_tree

ROOT = Path(__file__).resolve().parents[1]
DATE = "2011_09_26"
DRIVES = {"2011_09_26_drive_0001_sync": (0, 1, 2), "2011_09_26_drive_0002_sync": (3, 4)}


def run(args, code=0):
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    assert r.exit_code == code, r.output
    return r


def _kv(path: Path) -> dict:
    out = {}
    for line in path.read_text().splitlines():
        key, sep, value = line.partition(":")
        if sep:
            try:
                out[key.strip()] = np.array([float(v) for v in value.split()])
            except ValueError:
                pass
    return out


@pytest.fixture(scope="module")
def raw(real_dir, tmp_path_factory):
    """Two drives of the real frames, each frame with image_02 and image_03 (a copy)."""
    return make_raw_tree(real_dir, tmp_path_factory.mktemp("raw"), DRIVES,
                         cameras=("image_02", "image_03"))  # fmt: skip


@pytest.fixture(scope="module")
def kitti_rig(raw, tmp_path_factory):
    out = tmp_path_factory.mktemp("rig") / "ds"
    run(["dataset", "kitti-raw", raw, "-o", out, "--beams", "64", "--cameras",
         "image_02,image_03", "--store-geometry", "--splits", "0.5,0.5"])  # fmt: skip
    return out


def test_kitti_rig_keeps_every_camera_with_unique_ids(kitti_rig):
    ds = DatasetReader(kitti_rig)
    n_frames = sum(len(f) for f in DRIVES.values())
    assert len(ds) == 2 * n_frames
    assert len(set(ds.ids)) == len(ds)
    for drive, frames in DRIVES.items():
        for i in frames:
            for cam in ("image_02", "image_03"):
                r = ds.row(f"{drive}/{cam}/{i:010d}")
                assert (r.sequence, r.frame, r.camera) == (drive, f"{i:010d}", cam)
                assert r.rgb_path == f"rgb/{drive}/{cam}/{i:010d}.png"
    # the cameras of a frame share its rank; ranks count frames, not samples
    for drive, frames in DRIVES.items():
        idx = {
            ds.row(f"{drive}/{c}/{i:010d}").frame_index
            for i in frames
            for c in ("image_02", "image_03")
        }
        assert idx == set(range(len(frames)))
    # the copies of image_02 give image_03 the same pixels: both samples read back alike
    a = ds.sample(f"{drive}/image_02/{frames[0]:010d}")
    b = ds.sample(f"{drive}/image_03/{frames[0]:010d}")
    assert np.array_equal(a["rgb"], b["rgb"])
    assert not np.array_equal(a["sparse"], b["sparse"])  # another camera, another projection


def test_kitti_rig_splits_keep_cameras_and_drives_together(kitti_rig):
    ds = DatasetReader(kitti_rig)
    by_drive = {}
    for r in (ds.row(i) for i in range(len(ds))):
        by_drive.setdefault(r.sequence, set()).add(r.split)
    assert all(len(s) == 1 for s in by_drive.values())
    assert {s for v in by_drive.values() for s in v} == {"train", "val"}  # 2 drives, 0.5/0.5


def test_reader_returns_a_frames_cameras_together(kitti_rig):
    ds = DatasetReader(kitti_rig)
    drive = next(iter(DRIVES))
    cams = ds.cameras(f"{drive}/image_03/0000000001")
    assert sorted(cams) == ["image_02", "image_03"]
    assert cams["image_02"]["id"] == f"{drive}/image_02/0000000001"
    assert cams["image_03"]["camera"] == "image_03" and cams["image_03"]["frame"] == "0000000001"
    assert len(ds.frames()) == sum(len(f) for f in DRIVES.values())


def test_kitti_geometry_columns_are_the_calibrations_matrices(kitti_rig, raw):
    cam = _kv(raw / DATE / "calib_cam_to_cam.txt")
    velo = _kv(raw / DATE / "calib_velo_to_cam.txt")
    R_rect = np.eye(4)
    R_rect[:3, :3] = cam["R_rect_00"].reshape(3, 3)
    T_velo = np.eye(4)
    T_velo[:3, :3] = velo["R"].reshape(3, 3)
    T_velo[:3, 3] = velo["T"]
    ds = DatasetReader(kitti_rig)
    for n in (2, 3):
        P = cam[f"P_rect_0{n}"].reshape(3, 4)
        K = P[:, :3]
        # camera n's own rectified frame: shifted by K^-1 P[:, 3] from the reference camera's
        T = np.eye(4)
        T[:3, 3] = np.linalg.inv(K) @ P[:, 3]
        expected = T @ R_rect @ T_velo
        for i in range(len(ds)):
            r = ds.row(i)
            if r.camera != f"image_0{n}":
                continue
            g = ds.geometry(i)
            assert np.array_equal(g["intrinsics"], K)
            np.testing.assert_allclose(g["T_cam_lidar"], expected, rtol=0, atol=1e-12)
            # K @ T_cam_lidar projects as KITTI's P_rect @ R_rect @ [R|T] does
            np.testing.assert_allclose(K @ g["T_cam_lidar"][:3], P @ R_rect @ T_velo, atol=1e-9)
            assert r.baseline_m == pytest.approx((cam["P_rect_02"][3] - cam["P_rect_03"][3])
                                                 / cam["P_rect_02"][0], rel=1e-12)  # fmt: skip
            assert 0.53 < r.baseline_m < 0.54
            assert g["T_ego_cam"] is None and g["T_world_ego"] is None


def test_split_lists_keep_a_frames_cameras_together(raw, tmp_path):
    drive = next(iter(DRIVES))
    train = tmp_path / "train_files.txt"
    test = tmp_path / "test_files.txt"
    # frame 0: l in train, r in test (as the Eigen-Zhou lists do): both cameras go with l;
    # frame 1: r only, in test: both cameras in test; frame 2: in no list, left out
    train.write_text(f"{DATE}/{drive} 0 l\n")
    test.write_text(f"{DATE}/{drive} 0 r\n{DATE}/{drive} 1 r\n")
    out = tmp_path / "ds"
    run(["dataset", "kitti-raw", raw, "-o", out, "--beams", "64", "--cameras",
         "image_02,image_03", "--split-file", train, "--split-file", test])  # fmt: skip
    ds = DatasetReader(out)
    got = {i: ds.row(i).split for i in ds.ids}
    assert got == {
        f"{drive}/image_02/0000000000": "train", f"{drive}/image_03/0000000000": "train",
        f"{drive}/image_02/0000000001": "test", f"{drive}/image_03/0000000001": "test",
    }  # fmt: skip


def test_one_camera_build_writes_no_optional_column(raw, tmp_path):
    """The default keeps today's ids and manifest columns (tests/test_compat_v020.py holds the
    bytes); such a dataset reads with the geometry None."""
    out = tmp_path / "ds"
    run(["dataset", "kitti-raw", raw, "-o", out, "--beams", "64"])
    # neither the optional columns nor those of --store reference (REFERENCE_COLUMNS)
    expected = [n for n in MANIFEST_SCHEMA.names if n not in REFERENCE_COLUMNS]
    assert pq.read_schema(out / "manifest.parquet").names == expected
    ds = DatasetReader(out)
    assert ds.ids[0] == "2011_09_26_drive_0001_sync/0000000000"
    g = ds.geometry(0)
    assert g["T_cam_lidar"] is None and g["baseline_m"] is None and ds.row(0).camera is None
    assert g["intrinsics"] is not None  # from fx, fy, cx, cy as before
    assert ds.cameras(0).keys() == {None}


def test_bad_cameras_are_one_line_errors(raw, tmp_path):
    r = run(["dataset", "kitti-raw", raw, "-o", tmp_path / "a", "--cameras", "image_02,image_09"],
            code=1)  # fmt: skip
    assert "unknown camera 'image_09'" in r.output and "Traceback" not in r.output
    r = run(["dataset", "kitti-raw", raw, "-o", tmp_path / "b", "--cameras", "image_02,image_02"],
            code=1)  # fmt: skip
    assert "given twice" in r.output
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


# -- nuScenes, six cameras -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def nus_rig(real_dir, tmp_path_factory):
    root = tmp_path_factory.mktemp("nus") / "nuscenes"
    meta = build_tree(real_dir, root, cameras=CAMERAS)
    out = root.parent / "ds"
    run(["dataset", "nuscenes", root, "-o", out, "--cameras", "all", "--sensor", "LIDAR_TOP",
         "--gt-sensor", "none", "--store-points"])  # fmt: skip
    return out, meta


def test_nuscenes_tree_default_is_unchanged(real_dir, tmp_path):
    meta = build_tree(real_dir, tmp_path / "t")
    assert "cameras" not in meta
    assert sorted(p.name for p in (tmp_path / "t" / "samples").iterdir()) == [
        "CAM_FRONT", "LIDAR_TOP", "RADAR_FRONT"]  # fmt: skip


def test_nuscenes_six_cameras_with_their_geometry(nus_rig):
    out, meta = nus_rig
    ds = DatasetReader(out)
    assert len(ds) == 6 and len(set(ds.ids)) == 6
    assert {ds.row(i).camera for i in range(6)} == set(CAMERAS)
    assert len({ds.row(i).split for i in range(6)}) == 1  # one sample: one split
    info = json.loads((ROOT.parent / "shared/data/real/nuscenes-mmdet3d-demo/"
                       "calib_derived_from_pkl.json").read_text())  # fmt: skip
    for i in range(6):
        r = ds.row(i)
        assert r.id == f"scene-0061/{r.camera}/{r.frame}"
        c = meta["cameras"][r.camera]
        g = ds.geometry(i)
        np.testing.assert_allclose(g["intrinsics"], np.array(info["cameras"][r.camera]["cam2img"]),
                                   atol=1e-9)  # fmt: skip
        np.testing.assert_allclose(g["T_ego_cam"], c["cam2ego"], atol=1e-6)
        np.testing.assert_allclose(g["T_world_ego"], c["ego_cam"], atol=1e-6)
        # LiDAR -> camera through the ego poses at both times: the info's lidar2cam
        np.testing.assert_allclose(g["T_cam_lidar"], c["lidar2cam"], atol=1e-5)
    cams = ds.cameras(0)
    assert sorted(cams) == sorted(CAMERAS)
    assert all(s["rgb"].shape == (900, 1600, 3) for s in cams.values())


# -- loading ----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def no_gt(tmp_path_factory):
    """The synthetic sample frames built without ground truth (and without geometry)."""
    out = tmp_path_factory.mktemp("nogt")
    syn = ROOT / "sample_data" / "synthetic"
    run(["project", syn / "velodyne", "--calib", syn / "calib", "--image", syn / "image_2",
         "-o", out / "lidar", "--format", "parquet"])  # fmt: skip
    run(["dataset", "build", "-o", out / "ds", "--rgb", syn / "image_2", "--sparse",
         out / "lidar", "--calib", out / "lidar" / "calib"])  # fmt: skip
    return out / "ds"


def test_samples_without_gt_load_in_the_torch_dataset(no_gt):
    torch = pytest.importorskip("torch")
    from sparsetools.train.data import DepthDataset, SampleDataset

    ds = SampleDataset(no_gt)
    item = ds[0]
    assert item["has_gt"] is False and torch.count_nonzero(item["gt"]) == 0
    assert item["gt"].shape == item["sparse"].shape == (1, 375, 1242)
    assert torch.isfinite(item["K"]).all() and item["K"][2, 2] == 1
    assert torch.isnan(item["T_cam_lidar"]).all() and torch.isnan(item["baseline_m"])
    batch = torch.utils.data.default_collate([ds[0], ds[1]])
    assert batch["rgb"].shape == (2, 3, 375, 1242) and batch["has_gt"].tolist() == [False] * 2
    dd = DepthDataset(no_gt, "train", need_gt=False)
    assert torch.count_nonzero(dd[0]["gt"]) == 0


def test_dataloader_workers_give_the_same_tensors(kitti_rig):
    torch = pytest.importorskip("torch")
    from sparsetools.train.data import SampleDataset

    ds = SampleDataset(kitti_rig, split="train")

    def load(workers):
        loader = torch.utils.data.DataLoader(ds, batch_size=2, num_workers=workers)
        return list(loader)

    serial, parallel = load(0), load(2)
    assert len(serial) == len(parallel) > 0
    for a, b in zip(serial, parallel, strict=True):
        assert a.keys() == b.keys()
        for k in a:
            if isinstance(a[k], torch.Tensor):
                torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, equal_nan=True)
            else:
                assert a[k] == b[k], k
    first = serial[0]
    assert (
        first["T_cam_lidar"].dtype == torch.float64 and torch.isfinite(first["T_cam_lidar"]).all()
    )
    assert set(first["camera"]) <= {"image_02", "image_03"}
    assert first["has_gt"].all()


def test_optional_columns_are_listed_once():
    names = MANIFEST_SCHEMA.names + OPTIONAL_SCHEMA.names
    assert len(set(names)) == len(names)
    assert OPTIONAL_SCHEMA.field("T_cam_lidar").type.list_size == 16
    assert OPTIONAL_SCHEMA.field("K").type.list_size == 9


# -- stored points -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def with_points(raw, tmp_path_factory):
    out = tmp_path_factory.mktemp("pts") / "ds"
    run(["dataset", "kitti-raw", raw, "-o", out, "--beams", "64", "--cameras",
         "image_02,image_03", "--store-points"])  # fmt: skip
    return out


def _as_png(depth: np.ndarray) -> np.ndarray:
    """What the stored KITTI PNG holds of a float map (``project`` writes PNG maps)."""
    from sparsetools.io.image import decode_depth_png, encode_depth_png

    return decode_depth_png(encode_depth_png(depth)[0])


def _zbuffer(xyz, K, h, w):
    """A per-point restatement of the projection rule: rint pixel, 0.1 m < z, nearest wins."""
    out = np.zeros((h, w), np.float32)
    for x, y, z in xyz:
        if not z > 0.1:
            continue
        u = int(np.rint((K[0, 0] * x + K[0, 1] * y + K[0, 2] * z) / z))
        v = int(np.rint((K[1, 1] * y + K[1, 2] * z) / z))
        if 0 <= u < w and 0 <= v < h and (out[v, u] == 0 or np.float32(z) < out[v, u]):
            out[v, u] = np.float32(z)
    return out


def test_stored_points_reproject_to_the_stored_map(with_points):
    from sparsetools.train.transforms import reproject

    ds = DatasetReader(with_points)
    assert len(ds) == 2 * sum(len(f) for f in DRIVES.values())
    for i in range(len(ds)):
        s = ds.sample(i)
        xyz, ring = ds.points(i)
        assert xyz.dtype == np.float64 and ring.dtype == np.int16 and len(ring) == len(xyz)
        assert 0 <= ring.min() and ring.max() < 64
        h, w = s["sparse"].shape
        again = reproject(xyz, s["intrinsics"], h, w)
        # every stored point lands in the image, and the map is the stored one exactly (the
        # stored map is project's KITTI PNG: the same map, quantised to 1/256 m)
        assert np.array_equal(_as_png(again), s["sparse"])
        assert np.array_equal(_as_png(again), s["gt"])
        assert np.count_nonzero(again) == ds.row(i).n_sparse
        if i == 0:  # the rule written out point by point
            assert np.array_equal(_zbuffer(xyz, s["intrinsics"], h, w), again)
    g = ds.geometry(0)
    assert g["T_cam_lidar"] is not None  # --store-points implies --store-geometry


def test_stored_points_are_the_scan_in_the_camera_frame(with_points, raw):
    from sparsetools.io.pointcloud import read_points

    ds = DatasetReader(with_points)
    r = ds.row(0)
    scan = read_points(raw / DATE / r.sequence / "velodyne_points" / "data" / f"{r.frame}.bin")
    xyz, _ = ds.points(0)
    T = ds.geometry(0)["T_cam_lidar"]
    moved = scan[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    # each stored point is a scan point moved by T_cam_lidar (to rounding), none is invented
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(moved).query(xyz)
    assert dist.max() < 1e-9
    assert 0.05 * len(scan) < len(xyz) < 0.5 * len(scan)  # the image's field of view only


def test_random_beams_keeps_only_the_chosen_rings(with_points):
    from sparsetools.train.transforms import RandomBeams, reproject

    ds = DatasetReader(with_points)
    xyz, ring = ds.points(0)
    K = ds.geometry(0)["intrinsics"]
    h, w = ds.row(0).height, ds.row(0).width
    t = RandomBeams(keep=(1, 2, 4, 16), seed=0)
    seen = set()
    for k in range(12):
        rng = np.random.default_rng(k)
        depth, kept = t(xyz, ring, K, h, w, rng=rng)
        seen.add(len(kept))
        step = 64 // len(kept)
        assert len(kept) in (1, 2, 4, 16) and kept == tuple(range(kept[0], 64, step))
        # exactly the projection of the kept rings' points, nothing of the others
        assert np.array_equal(depth, reproject(xyz[np.isin(ring, kept)], K, h, w))
        others = reproject(xyz[~np.isin(ring, kept)], K, h, w)
        only_others = (others > 0) & (depth == 0)
        assert np.count_nonzero(depth) < np.count_nonzero(reproject(xyz, K, h, w))
        assert only_others.any()
        # the same generator state draws the same rings
        assert t(xyz, ring, K, h, w, rng=np.random.default_rng(k))[1] == kept
    assert len(seen) > 1
    with pytest.raises(Exception, match="divide 64"):
        RandomBeams(keep=(3,))
    with pytest.raises(Exception, match="rings"):
        t(xyz, None, K, h, w)


def test_dataset_build_stores_the_calibrations_geometry(tmp_path):
    """``dataset build --calib`` with --store-geometry: K and T_cam_lidar of the frame's own
    calibration file (KITTI object form: P2, R0_rect, Tr_velo_to_cam)."""
    syn = ROOT / "sample_data" / "synthetic"
    run(["project", syn / "velodyne", "--calib", syn / "calib", "--image", syn / "image_2",
         "-o", tmp_path / "lidar"])  # fmt: skip
    out = tmp_path / "ds"
    run(["dataset", "build", "-o", out, "--rgb", syn / "image_2", "--sparse", tmp_path / "lidar",
         "--calib", syn / "calib", "--store-geometry"])  # fmt: skip
    ds = DatasetReader(out)
    for i in range(len(ds)):
        kv = _kv(syn / "calib" / f"{ds.row(i).frame}.txt")
        P = kv["P2"].reshape(3, 4)
        R0 = np.eye(4)
        R0[:3, :3] = kv["R0_rect"].reshape(3, 3)
        Tr = np.vstack([kv["Tr_velo_to_cam"].reshape(3, 4), [0, 0, 0, 1]])
        g = ds.geometry(i)
        assert np.array_equal(g["intrinsics"], P[:, :3])
        np.testing.assert_allclose(g["intrinsics"] @ g["T_cam_lidar"][:3], P @ R0 @ Tr, atol=1e-9)
        assert g["baseline_m"] is None  # no stereo pair in an object calibration
    # a rerun without the option is refused, naming it
    r = run(["dataset", "build", "-o", out, "--rgb", syn / "image_2", "--sparse",
             tmp_path / "lidar", "--calib", syn / "calib"], code=1)  # fmt: skip
    assert "--store-geometry" in r.output


def test_points_parts_resume_and_split(raw, tmp_path, monkeypatch):
    """A rerun is a no-op; parts hold at most POINTS_PER_PART samples; --overwrite rewrites
    them and leaves no part that no row refers to."""
    import sparsetools.pipeline.dataset.merge as merge

    monkeypatch.setattr(merge, "POINTS_PER_PART", 3)
    out = tmp_path / "ds"
    args = ["dataset", "kitti-raw", raw, "-o", out, "--beams", "64", "--store-points"]
    run(args)
    parts = sorted(p.name for p in (out / "points").iterdir())
    assert parts == ["part-00000.parquet", "part-00001.parquet"]  # 5 samples, 3 + 2
    manifest = (out / "manifest.parquet").read_bytes()
    r = CliRunner().invoke(cli, ["-q", *map(str, args), "--json"])
    assert json.loads(r.stdout)["processed"] == 0
    assert (out / "manifest.parquet").read_bytes() == manifest
    run([*args, "--overwrite"])
    ds = DatasetReader(out)
    referenced = {ds.row(i).points_parquet for i in range(len(ds))}
    assert {f"points/{p.name}" for p in (out / "points").iterdir()} == referenced
    for i in range(len(ds)):  # every row still finds its own points
        s = ds.sample(i)
        xyz, _ = ds.points(i)
        from sparsetools.train.transforms import reproject

        assert np.array_equal(_as_png(reproject(xyz, s["intrinsics"], *s["sparse"].shape)),
                              s["sparse"])  # fmt: skip


def test_the_documented_torch_recipe_loads_samples_without_gt(no_gt):
    """The DepthDataset of docs/dataset.md ("Loading"), run as written on a dataset without
    ground truth, through a DataLoader with two workers."""
    torch = pytest.importorskip("torch")
    text = (ROOT / "docs" / "dataset.md").read_text()
    start = text.index("NAN4 = np.full")
    block = text[text.rindex("```python", 0, start) + len("```python") : text.index("```", start)]
    block = block.replace('"out/ds"', repr(str(no_gt))).replace('"train"', "None")
    scope: dict = {}
    exec(compile(block, "docs/dataset.md", "exec"), scope)
    batch = next(iter(scope["loader"]))
    assert batch["has_gt"].tolist() == [False, False]
    assert torch.count_nonzero(batch["gt"]) == 0 and batch["K"].shape == (2, 3, 3)
    assert torch.isnan(batch["T_cam_lidar"]).all()


def test_nuscenes_one_camera_geometry_keeps_todays_ids(real_dir, tmp_path):
    root = tmp_path / "nuscenes"
    meta = build_tree(real_dir, root, cameras=("CAM_FRONT", "CAM_BACK"))
    out = tmp_path / "ds"
    run(["dataset", "nuscenes", root, "-o", out, "--gt-sensor", "none", "--store-geometry"])
    ds = DatasetReader(out)
    assert len(ds) == 1 and ds.ids[0] == f"scene-0061/{ds.row(0).frame}"  # CAM_FRONT only
    assert ds.row(0).camera is None
    c = meta["cameras"]["CAM_FRONT"]
    g = ds.geometry(0)
    np.testing.assert_allclose(g["T_ego_cam"], c["cam2ego"], atol=1e-6)
    np.testing.assert_allclose(g["T_world_ego"], c["ego_cam"], atol=1e-6)
    # the sparse input is RADAR_FRONT: T_cam_lidar is the radar -> camera chain, not LiDAR
    assert g["T_cam_lidar"] is not None and not np.allclose(g["T_cam_lidar"], c["lidar2cam"])
    assert ds.row(0).source == "radar_front"


def test_a_camera_missing_for_some_frames_is_counted(raw, tmp_path):
    part = tmp_path / "raw"
    shutil.copytree(raw, part)
    drive = next(iter(DRIVES))
    (part / DATE / drive / "image_03" / "data" / "0000000001.png").unlink()
    out = tmp_path / "ds"
    r = CliRunner().invoke(cli, ["-q", "dataset", "kitti-raw", str(part), "-o", str(out),
                                 "--beams", "64", "--cameras", "image_02,image_03", "--json"])  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    n = sum(len(f) for f in DRIVES.values())
    assert summary["samples"] == 2 * n - 1 and summary["unmatched"]["missing_camera"] == 1
    ds = DatasetReader(out)
    assert sorted(ds.cameras(f"{drive}/image_02/0000000001")) == ["image_02"]
    # a camera with no image at all is refused before any stage runs
    for p in (part / DATE).glob("*/image_03"):
        shutil.rmtree(p)
    out2 = tmp_path / "ds2"
    r = run(["dataset", "kitti-raw", part, "-o", out2, "--cameras", "image_02,image_03"],
            code=1)  # fmt: skip
    assert "--cameras" in r.output and "image_03" in r.output
    assert not (out2 / ".sources").exists()


def test_nuscenes_stored_points_reproject_to_each_cameras_map(nus_rig):
    """LIDAR_TOP of the demo sample, stored for each of the six cameras: re-projected with
    each camera's K, the camera's stored map; the rings are the .pcd.bin's ring column."""
    from sparsetools.train.transforms import reproject

    out, _ = nus_rig
    ds = DatasetReader(out)
    sizes = []
    for i in range(len(ds)):
        s = ds.sample(i)
        xyz, ring = ds.points(i)
        assert ring is not None and 0 <= ring.min() and ring.max() < 32
        again = reproject(xyz, s["intrinsics"], *s["sparse"].shape)
        assert np.array_equal(_as_png(again), s["sparse"])
        assert np.count_nonzero(again) == ds.row(i).n_sparse > 0
        sizes.append(len(xyz))
    assert len(set(sizes)) == 6  # six cameras, six different fields of view


def test_nuscenes_radar_points_with_resize_and_crop(real_dir, tmp_path):
    """The radar paper's setting (800x450, top 100 rows cut): the 61 devkit-filtered radar
    points that land, without rings, re-project with the stored (resized, cropped) K to the
    stored map."""
    from sparsetools.train.transforms import reproject

    root = tmp_path / "nuscenes"
    build_tree(real_dir, root)
    out = tmp_path / "ds"
    run(["dataset", "nuscenes", root, "-o", out, "--store-points", "--resize", "0.5",
         "--crop", "800x350+0+100"])  # fmt: skip
    ds = DatasetReader(out)
    s = ds.sample(0)
    xyz, ring = ds.points(0)
    assert ring is None and len(xyz) == 61 and s["sparse"].shape == (350, 800)
    assert np.array_equal(_as_png(reproject(xyz, s["intrinsics"], 350, 800)), s["sparse"])
