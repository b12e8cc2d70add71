"""Real dataset trees: a KITTI raw date folder with two drives whose frame names collide, and a
KITTI depth-completion tree (train and val, two drives) built from the real KITTI sequence.

Every frame is kept, outputs are per sequence (drive), and a rerun is a no-op."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli

pytestmark = pytest.mark.real

DATE = "2011_09_26"
DRIVES = (f"{DATE}_drive_0001_sync", f"{DATE}_drive_0002_sync")
N = 3  # frames per drive


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def summary(*args) -> dict:
    r = run(*args, "--json")
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def raw_root(real_dir, tmp_path_factory):
    """raw/2011_09_26/{calib, drive_0001 (frames 0-2), drive_0002 (frames 3-5 renamed 0-2)}."""
    seq = real_dir / "kitti-raw-sequence-2011_09_26"
    root = tmp_path_factory.mktemp("raw")
    date = root / DATE
    date.mkdir()
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(seq / name, date / name)
    for d, drive in enumerate(DRIVES):
        for i in range(N):
            src = f"{d * N + i:010d}"
            dst = f"{i:010d}"  # the same names in both drives
            for sub, ext in (("velodyne_points", ".bin"), ("image_02", ".png")):
                folder = date / drive / sub / "data"
                folder.mkdir(parents=True, exist_ok=True)
                shutil.copy(seq / sub / "data" / f"{src}{ext}", folder / f"{dst}{ext}")
    return root


def test_project_and_beams_keep_every_frame_per_drive(raw_root, tmp_path):
    out = tmp_path / "lidar"
    s = summary("project", raw_root / DATE, "-o", out)
    assert s["frames"] == s["processed"] == 2 * N
    maps = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.png"))
    assert maps == [f"{drive}/{i:010d}.png" for drive in DRIVES for i in range(N)]
    # the two drives' frame 0 are different scans, so different maps
    a, b = (out / drive / "0000000000.png" for drive in DRIVES)
    assert a.read_bytes() != b.read_bytes()
    # a rerun is a no-op
    again = summary("project", raw_root / DATE, "-o", out)
    assert again["processed"] == 0 and again["skipped_existing"] == 2 * N

    beams = tmp_path / "b4"
    s = summary("beams", raw_root / DATE, "--n", "4", "-o", beams)
    assert s["frames"] == s["processed"] == 2 * N and s["rings_n4"] == "7,10,12,14"
    clouds = sorted(p.relative_to(beams).as_posix() for p in beams.rglob("*.bin"))
    assert clouds == [f"{drive}/{i:010d}.bin" for drive in DRIVES for i in range(N)]
    assert summary("beams", raw_root / DATE, "--n", "4", "-o", beams)["processed"] == 0
    # the beams output projects with the raw tree's calibration, per drive again
    b4 = tmp_path / "b4_depth"
    s = summary("project", beams, "--calib", raw_root / DATE, "-o", b4)
    assert s["frames"] == 2 * N and sorted(p.parent.name for p in b4.rglob("*.png")) == sorted(
        [DRIVES[0]] * N + [DRIVES[1]] * N
    )


def _dc_tree(root: Path, sparse: Path, gt: Path) -> Path:
    """data_depth_{velodyne,annotated}/{train,val}/<drive>/proj_depth/<name>/image_02/*.png;
    drive 1 in train, drive 2 in val; ground truth for all frames but the first of drive 1."""
    dc = root / "kitti_dc"
    for drive, split in zip(DRIVES, ("train", "val"), strict=True):
        for name, src_root, kind in (
            ("velodyne_raw", sparse, "data_depth_velodyne"),
            ("groundtruth", gt, "data_depth_annotated"),
        ):
            folder = dc / kind / split / drive / "proj_depth" / name / "image_02"
            folder.mkdir(parents=True)
            for i in range(N):
                if name == "groundtruth" and drive == DRIVES[0] and i == 0:
                    continue  # KITTI's first frames have no accumulated ground truth
                shutil.copy(src_root / drive / f"{i:010d}.png", folder / f"{i:010d}.png")
    return dc


def test_dataset_build_from_a_depth_completion_tree_keeps_every_frame(raw_root, tmp_path):
    full, b4 = tmp_path / "full", tmp_path / "b4"
    assert run("project", raw_root / DATE, "-o", full).exit_code == 0
    assert run("beams", raw_root / DATE, "--n", "4", "-o", tmp_path / "b4c").exit_code == 0
    assert run("project", tmp_path / "b4c", "--calib", raw_root / DATE, "-o", b4).exit_code == 0
    dc = _dc_tree(tmp_path, sparse=b4, gt=full)
    ds = tmp_path / "ds"
    args = ["dataset", "build", "-o", ds, "--rgb", raw_root / DATE,
            "--sparse", dc / "data_depth_velodyne", "--gt", dc / "data_depth_annotated",
            "--split", "tree"]  # fmt: skip
    s = summary(*args)
    # every frame with ground truth is kept; the one without is reported, not silently lost
    assert s["samples"] == 2 * N - 1 and s["processed"] == 2 * N - 1
    assert s["unmatched"] == {"rgb_without_sparse": 0, "without_gt": 1, "without_tree_split": 0}
    assert s["sequences"] == 2 and s["splits"] == {"train": N - 1, "val": N}

    from sparsetools.io.dataset_reader import DatasetReader

    reader = DatasetReader(ds)
    ids = sorted(reader.manifest.column("id").to_pylist())
    expected = [f"{d}/{i:010d}" for d in DRIVES for i in range(N) if (d, i) != (DRIVES[0], 0)]
    assert ids == expected
    rows = {r["id"]: r for r in reader.manifest.to_pylist()}
    row = rows[f"{DRIVES[1]}/0000000000"]
    assert row["sequence"] == DRIVES[1] and row["frame"] == "0000000000"
    assert row["fx"] == pytest.approx(721.5377) and row["split"] == "val"
    assert [rows[i]["frame_index"] for i in ids] == [0, 1, 0, 1, 2]
    # the sample holds its own drive's data (frame names collide across drives)
    sample = reader.sample(f"{DRIVES[1]}/0000000000")
    src = raw_root / DATE / DRIVES[1] / "image_02" / "data" / "0000000000.png"
    import cv2

    assert np.array_equal(sample["rgb"], cv2.cvtColor(cv2.imread(str(src)), cv2.COLOR_BGR2RGB))
    # a rerun is a no-op, and the dataset verifies
    again = summary(*args)
    assert again["processed"] == 0 and again["skipped_existing"] == 2 * N - 1
    r = run("dataset", "verify", ds)
    assert r.exit_code == 0, r.output
