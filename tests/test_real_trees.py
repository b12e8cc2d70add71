"""Real dataset trees: a KITTI raw date folder with two drives whose frame names collide, and a
KITTI depth-completion tree (train and val, two drives) built from the real KITTI sequence.

Every frame is kept, outputs are per sequence (drive), and a rerun is a no-op."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from _cli import run, summary
from _kitti_raw_tree import make_raw_tree

pytestmark = pytest.mark.real

DATE = "2011_09_26"
DRIVES = (f"{DATE}_drive_0001_sync", f"{DATE}_drive_0002_sync")
N = 3  # frames per drive


@pytest.fixture(scope="module")
def raw_root(real_dir, tmp_path_factory):
    """raw/2011_09_26/{calib, drive_0001 (frames 0-2), drive_0002 (frames 3-5 renamed 0-2)}."""
    drives = {drive: [(d * N + i, i) for i in range(N)] for d, drive in enumerate(DRIVES)}
    return make_raw_tree(real_dir, tmp_path_factory.mktemp("raw"), drives)


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
            "--splits", "tree"]  # fmt: skip
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


def test_kitti_raw_route_in_one_command(raw_root, tmp_path):
    ds = tmp_path / "ds"
    args = ["dataset", "kitti-raw", raw_root / DATE, "-o", ds, "--beams", "4"]
    s = summary(*args)
    assert s["samples"] == 2 * N and s["sequences"] == 2 and s["failed"] == 0
    from sparsetools.io.dataset_reader import DatasetReader

    rows = DatasetReader(ds).manifest.to_pylist()
    assert {r["source"] for r in rows} == {"lidar-4beam"}
    assert all(0 < r["n_sparse"] < r["n_gt"] for r in rows)
    assert sorted({r["sequence"] for r in rows}) == list(DRIVES)
    assert all(r["fx"] == pytest.approx(721.5377) for r in rows)
    again = summary(*args)
    assert again["processed"] == 0 and again["skipped_existing"] == 2 * N


def test_kitti_dc_route_and_selection(raw_root, tmp_path):
    full, b4 = tmp_path / "full", tmp_path / "b4"
    assert run("project", raw_root / DATE, "-o", full).exit_code == 0
    assert run("beams", raw_root / DATE, "--n", "4", "-o", tmp_path / "b4c").exit_code == 0
    assert run("project", tmp_path / "b4c", "--calib", raw_root / DATE, "-o", b4).exit_code == 0
    dc = _dc_tree(tmp_path, sparse=b4, gt=full)
    s = summary("dataset", "kitti-dc", dc, "--raw", raw_root / DATE, "-o", tmp_path / "ds")
    assert s["samples"] == 2 * N - 1 and s["splits"] == {"train": N - 1, "val": N}
    assert s["unmatched"]["without_gt"] == 1

    # val_selection_cropped: <drive>_<kind>_<frame>_image_02.<ext> with its own intrinsics
    sel = dc / "depth_selection" / "val_selection_cropped"
    for sub in ("image", "velodyne_raw", "groundtruth_depth", "intrinsics"):
        (sel / sub).mkdir(parents=True)
    drive, frame = DRIVES[1], "0000000001"
    stem = f"{drive}_{{kind}}_{frame}_image_02"
    shutil.copy(raw_root / DATE / drive / "image_02" / "data" / f"{frame}.png",
                sel / "image" / f"{stem.format(kind='image')}.png")  # fmt: skip
    shutil.copy(b4 / drive / f"{frame}.png",
                sel / "velodyne_raw" / f"{stem.format(kind='velodyne_raw')}.png")  # fmt: skip
    shutil.copy(full / drive / f"{frame}.png",
                sel / "groundtruth_depth" / f"{stem.format(kind='groundtruth_depth')}.png")  # fmt: skip
    (sel / "intrinsics" / f"{stem.format(kind='image')}.txt").write_text(
        "7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 7.215377e+02 1.728540e+02 "
        "0.000000e+00 0.000000e+00 1.000000e+00\n"
    )
    s = summary("dataset", "kitti-dc", dc, "--selection", "-o", tmp_path / "sel")
    assert s["samples"] == 1 and s["splits"] == {"val_selection": 1}
    from sparsetools.io.dataset_reader import DatasetReader

    (row,) = DatasetReader(tmp_path / "sel").manifest.to_pylist()
    assert row["id"] == f"{drive}/{frame}" and row["cy"] == pytest.approx(172.854)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (["dataset", "kitti-dc", "{empty}", "--raw", "{raw}"], "not a KITTI depth-completion tree"),
        (["dataset", "kitti-raw", "{empty}"], "not a KITTI raw drive, date folder or root"),
    ],
)
def test_bad_roots_are_one_line(raw_root, tmp_path, args, match):
    empty = tmp_path / "empty"
    empty.mkdir()
    args = [a.format(empty=empty, raw=raw_root / DATE) for a in args]
    r = run(*args, "-o", tmp_path / "ds")
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1 and match in lines[0], r.output


def _read_official_layout(root: Path, name: str) -> dict[tuple[str, str, str], Path]:
    """A straightforward reader of the KITTI depth-completion layout, as other code reads it:
    {split}/{drive}/proj_depth/{name}/image_02/{frame}.png."""
    out = {}
    for split in ("train", "val"):
        for drive_dir in sorted((root / split).iterdir()) if (root / split).is_dir() else []:
            folder = drive_dir / "proj_depth" / name / "image_02"
            for f in sorted(folder.glob("*.png")):
                out[(split, drive_dir.name, f.stem)] = f
    return out


def test_export_writes_the_official_layout(raw_root, tmp_path):
    full, b4 = tmp_path / "full", tmp_path / "b4"
    assert run("project", raw_root / DATE, "-o", full).exit_code == 0
    assert run("beams", raw_root / DATE, "--n", "4", "-o", tmp_path / "b4c").exit_code == 0
    assert run("project", tmp_path / "b4c", "--calib", raw_root / DATE, "-o", b4).exit_code == 0
    dc = _dc_tree(tmp_path, sparse=b4, gt=full)
    out = tmp_path / "export"
    s = summary("dataset", "export", b4, "-o", out, "--name", "velodyne_raw_4beam",
                "--split-from", dc / "data_depth_velodyne")  # fmt: skip
    assert s["frames"] == 2 * N
    found = _read_official_layout(out, "velodyne_raw_4beam")
    assert sorted(found) == sorted(
        (split, d, f"{i:010d}") for d, split in zip(DRIVES, ("train", "val"), strict=True)
        for i in range(N)
    )  # fmt: skip
    for (_, drive, frame), path in found.items():
        assert path.read_bytes() == (b4 / drive / f"{frame}.png").read_bytes()
    # the exported tree is itself a depth-completion tree the dataset route reads
    s = summary("dataset", "kitti-dc", out, "--raw", raw_root / DATE, "-o", tmp_path / "ds",
                "--sparse-name", "velodyne_raw_4beam")  # fmt: skip
    assert s["samples"] == 2 * N and s["splits"] == {"train": N, "val": N}
    sel = summary("dataset", "export", b4, "-o", tmp_path / "sel", "--layout", "kitti-selection",
                  "--name", "velodyne_raw")  # fmt: skip
    assert sel["frames"] == 2 * N
    assert (tmp_path / "sel" / "velodyne_raw"
            / f"{DRIVES[0]}_velodyne_raw_0000000001_image_02.png").is_file()  # fmt: skip
