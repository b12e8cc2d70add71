"""Regenerate the pictures of docs/project.md with the project itself.

Run from the repository root: ``.venv/bin/python docs/img/make_project.py``.

- ``project_kitti.png``: ``sparsetools project --kitti-object sample_data/kitti`` (the real KITTI
  frame 000001), sparse depth coloured 0-80 m over the camera image; ``project_kitti_map.png``:
  the map alone.
- ``project_nuscenes.png``: the real nuScenes LIDAR_TOP sweep projected to CAM_FRONT at the
  radar papers' 800x450 resolution, then their 350x800 crop (top 100 rows removed).
- ``project_occluded.png``: ``--filter-occluded`` on the real KITTI frame 000001: the kept
  points coloured by depth over the image, the removed ones in magenta (3x3).
- ``project_radar.png``: the 5 merged front-radar sweeps (nuScenes radar PCD) of
  ``sample_data/synthetic`` frame 000000 with its JSON calibration.

The nuScenes picture needs ../shared/data/real (skipped when absent).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.image import read_depth_png, read_image
from sparsetools.ops.colormap import colorize_depth, overlay_depth

HERE = Path(__file__).resolve().parent
SAMPLE = HERE.parent.parent / "sample_data"
REAL = HERE.parent.parent.parent / "shared" / "data" / "real"


def sparsetools(*args) -> None:
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    if r.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{r.stderr}")


def save(name: str, rgb: np.ndarray) -> None:
    # The highest zlib level (and a reduced size) keeps each picture under 400 KB.
    ok, buf = cv2.imencode(".png", rgb[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    (HERE / name).write_bytes(buf.tobytes())
    print(f"{name}: {rgb.shape[1]}x{rgb.shape[0]}, {len(buf) // 1024} KB")


def kitti(tmp: Path) -> None:
    src = SAMPLE / "kitti"
    sparsetools("project", "--kitti-object", src, "-o", tmp / "kitti")
    depth = read_depth_png(tmp / "kitti" / "000001.png")
    image = read_image(src / "image_2" / "000001.png")
    overlay = overlay_depth(image, depth, max_depth=80.0, dilate=1)
    save(
        "project_kitti.png",
        cv2.resize(overlay, None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA),
    )
    # The map alone, bottom half (no LiDAR hits above the horizon), points grown to 2x2.
    alone = colorize_depth(cv2.dilate(depth, np.ones((2, 2), np.uint8)), max_depth=80.0)
    save("project_kitti_map.png", alone[150:])


def nuscenes(tmp: Path) -> None:
    src = REAL / "nuscenes-mmdet3d-demo"
    cloud = next(src.glob("*LIDAR_TOP*.pcd.bin"))
    image_path = next(src.glob("*__CAM_FRONT__*.jpg"))
    sparsetools(
        "project",
        cloud,
        "--calib",
        src / "calib_derived_from_pkl.json",
        "--camera",
        "CAM_FRONT",
        "--resize",
        "0.5",
        "--crop",
        "100,0,350,800",
        "--min-depth",
        "1",
        "-o",
        tmp / "nuscenes",
    )
    stem = cloud.name[: -len(".pcd.bin")]
    depth = read_depth_png(tmp / "nuscenes" / f"{stem}.png")
    image = cv2.resize(read_image(image_path), (800, 450), interpolation=cv2.INTER_AREA)[100:]
    save("project_nuscenes.png", overlay_depth(image, depth, max_depth=80.0, dilate=1))


def radar(tmp: Path) -> None:
    scene = SAMPLE / "synthetic"
    sparsetools(
        "project",
        scene / "radar" / "000000.pcd",
        "--calib",
        scene / "calib_radar" / "000000.json",
        "-o",
        tmp / "radar",
    )
    depth = read_depth_png(tmp / "radar" / "000000.png")
    image = read_image(scene / "image_2" / "000000.png")
    save(
        "project_radar.png",
        cv2.resize(
            overlay_depth(image, depth, max_depth=80.0, dilate=3),
            None,
            fx=0.75,
            fy=0.75,
            interpolation=cv2.INTER_AREA,
        ),
    )


def occluded(tmp: Path) -> None:
    src = SAMPLE / "kitti"
    sparsetools("project", "--kitti-object", src, "-o", tmp / "plain")
    sparsetools("project", "--kitti-object", src, "-o", tmp / "filtered", "--filter-occluded")
    plain = read_depth_png(tmp / "plain" / "000001.png")
    kept = read_depth_png(tmp / "filtered" / "000001.png")
    removed = (plain > 0) & (kept == 0)
    image = read_image(src / "image_2" / "000001.png")
    overlay = overlay_depth(image, kept, max_depth=80.0, dilate=1)
    grown = cv2.dilate(removed.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    overlay[grown] = (255, 0, 255)
    save("project_occluded.png",
         cv2.resize(overlay, None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA))  # fmt: skip
    print(f"removed {int(removed.sum())} of {int((plain > 0).sum())} pixels")


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as d:
        kitti(Path(d))
        occluded(Path(d))
        radar(Path(d))
        if REAL.is_dir():
            nuscenes(Path(d))
        else:
            print(f"{REAL} not found: skipping the nuScenes picture")
