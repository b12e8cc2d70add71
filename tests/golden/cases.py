"""One canonical invocation of every batch command, in 0.2.0's spelling (``old``) and today's
(``new``). Placeholders: ``{S}`` sample_data/synthetic, ``{K}`` sample_data/kitti, ``{D}`` the
derived inputs below, ``{R}`` ../shared/data/real (cases marked ``real``), ``{O}`` the output.
"""

from __future__ import annotations

import shutil
from pathlib import Path

DATE = "2011_09_26"
DRIVE = "2011_09_26_drive_0001_sync"


def make_raw_tree(real: Path, dest: Path) -> None:
    """``dest/2011_09_26/<drive>``: frames 0-2 of the real KITTI raw sequence."""
    seq = real / "kitti-raw-sequence-2011_09_26"
    date = dest / DATE
    date.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(seq / name, date / name)
    for i in range(3):
        for sub, ext in (("velodyne_points", ".bin"), ("image_02", ".png")):
            folder = date / DRIVE / sub / "data"
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copy(seq / sub / "data" / f"{i:010d}{ext}", folder / f"{i:010d}{ext}")


#: Inputs made first (folders under ``{D}``), in this order; ``raw_lidar`` needs ``{D}/raw``
#: (:func:`make_raw_tree`, from the real data).
DERIVED = {
    "lidar": ["project", "{S}/velodyne", "--calib", "{S}/calib", "--image-size", "1242x375",
              "-o", "{O}"],
    "radar_depth": ["project", "{S}/radar/000000.pcd", "{S}/radar/000001.pcd",
                    "{S}/radar/000002.pcd", "--calib", "{S}/calib_radar", "-o", "{O}"],
    "raw_lidar": ["project", "{D}/raw/2011_09_26", "-o", "{O}"],
}  # fmt: skip


def _same(args: list[str], **kw) -> dict:
    return {"old": args, "new": args, **kw}


CASES = {
    "project_png": _same(
        ["project", "{S}/velodyne", "--calib", "{S}/calib", "--image-size", "1242x375", "-o", "{O}"]
    ),
    "project_npy_crop": {
        "old": [
            "project",
            "{S}/velodyne",
            "--calib",
            "{S}/calib",
            "--image-size",
            "1242x375",
            "--format",
            "npy",
            "--resize",
            "0.5",
            "--crop",
            "20,10,150,600",
            "--max-depth",
            "60",
            "-o",
            "{O}",
        ],
        "new": [
            "project",
            "{S}/velodyne",
            "--calib",
            "{S}/calib",
            "--image-size",
            "1242x375",
            "--format",
            "npy",
            "--resize",
            "0.5",
            "--crop",
            "600x150+10+20",
            "--max-depth",
            "60",
            "-o",
            "{O}",
        ],
    },
    "project_parquet": _same(
        [
            "project",
            "{S}/velodyne",
            "--calib",
            "{S}/calib",
            "--image-size",
            "1242x375",
            "--format",
            "parquet",
            "-o",
            "{O}",
        ]
    ),
    "project_kitti_md2": _same(
        [
            "project",
            "{K}/velodyne",
            "--calib",
            "{K}/calib",
            "--image",
            "{K}/image_2",
            "--pixel-offset",
            "-1",
            "-o",
            "{O}",
        ]
    ),
    "beams_multi": _same(
        [
            "beams",
            "{K}/velodyne",
            "--n",
            "1,2,4,16",
            "--calib",
            "{K}/calib",
            "--image",
            "{K}/image_2",
            "-o",
            "{O}",
        ]
    ),
    "beams_plpp": _same(
        [
            "beams",
            "{K}/velodyne",
            "--select",
            "pl++",
            "--n",
            "4",
            "--calib",
            "{K}/calib",
            "--image",
            "{K}/image_2",
            "-o",
            "{O}",
        ]
    ),
    "beams_synth_4_npy": _same(
        ["beams", "{S}/velodyne", "--n", "4", "--format", "npy", "-o", "{O}"]
    ),
    "jbf_expand": {
        "old": [
            "jbf-expand",
            "{D}/radar_depth",
            "--image",
            "{S}/image_2",
            "--calib",
            "{S}/calib_radar",
            "--lidar",
            "{D}/lidar",
            "--window",
            "1x2",
            "-o",
            "{O}",
        ],
        "new": [
            "jbf-expand",
            "{D}/radar_depth",
            "--image",
            "{S}/image_2",
            "--calib",
            "{S}/calib_radar",
            "--lidar",
            "{D}/lidar",
            "--window-m",
            "1x2",
            "-o",
            "{O}",
        ],
    },
    "jbf_expand_height_noconf": {
        "old": [
            "jbf-expand",
            "{S}/radar/000000.pcd",
            "--image",
            "{S}/image_2/000000.png",
            "--calib",
            "{S}/calib_radar/000000.json",
            "--method",
            "height-extend",
            "--no-confidence",
            "--resize",
            "0.5",
            "-o",
            "{O}",
        ],
        "new": [
            "jbf-expand",
            "{S}/radar/000000.pcd",
            "--image",
            "{S}/image_2/000000.png",
            "--calib",
            "{S}/calib_radar/000000.json",
            "--method",
            "height-extend",
            "--conf-format",
            "none",
            "--resize",
            "0.5",
            "-o",
            "{O}",
        ],
    },
    "lowlight": {
        "old": [
            "lowlight-synth",
            "{S}/image_2",
            "--depth",
            "{S}/depth_gt",
            "--calib",
            "{S}/calib",
            "--camera",
            "NikonD850",
            "--seed",
            "3",
            "--variants",
            "2",
            "-o",
            "{O}",
        ],
        "new": [
            "lowlight-synth",
            "{S}/image_2",
            "--depth",
            "{S}/depth_gt",
            "--calib",
            "{S}/calib",
            "--noise-profile",
            "NikonD850",
            "--seed",
            "3",
            "--variants",
            "2",
            "-o",
            "{O}",
        ],
    },
    "equalize": {
        "old": [
            "equalize",
            "{S}/image_2",
            "--reference",
            "000001",
            "--rounding",
            "rnw",
            "-o",
            "{O}",
        ],
        "new": [
            "equalize",
            "{S}/image_2",
            "--reference-frame",
            "000001",
            "--rounding",
            "rnw",
            "-o",
            "{O}",
        ],
    },
    "underwater": {
        "old": [
            "underwater",
            "{S}/underwater/seafloor",
            "--water",
            "{S}/underwater/water",
            "--window",
            "5",
            "-o",
            "{O}",
        ],
        "new": [
            "underwater",
            "{S}/underwater/seafloor",
            "--water",
            "{S}/underwater/water",
            "--median-window",
            "5",
            "-o",
            "{O}",
        ],
    },
    "defocus": {
        "old": [
            "defocus-synth",
            "{S}/image_2",
            "--depth",
            "{S}/depth_gt",
            "--missing-depth",
            "far",
            "--sensor",
            "dfd-nyu",
            "--camera",
            "SonyA7S2",
            "--seed",
            "1",
            "-o",
            "{O}",
        ],
        "new": [
            "defocus-synth",
            "{S}/image_2",
            "--depth",
            "{S}/depth_gt",
            "--missing-depth",
            "far",
            "--lens",
            "dfd-nyu",
            "--noise-profile",
            "SonyA7S2",
            "--seed",
            "1",
            "-o",
            "{O}",
        ],
    },
    "dark_channel": {
        "old": [
            "dark-channel",
            "{S}/image_2",
            "--window",
            "7",
            "--lddcv-format",
            "png",
            "--mask-mode",
            "separate",
            "--save-pictures",
            "-o",
            "{O}",
        ],
        "new": [
            "dark-channel",
            "{S}/image_2",
            "--patch-size",
            "7",
            "--lddcv-format",
            "png",
            "--mask-mode",
            "separate",
            "--save-pictures",
            "-o",
            "{O}",
        ],
    },
    "densify": {
        "old": ["densify", "{D}/lidar", "--max-depth", "90", "--multiscale", "-o", "{O}"],
        "new": ["densify", "{D}/lidar", "--inversion-offset", "90", "--multiscale", "-o", "{O}"],
    },
    "densify_linear_npy": _same(
        ["densify", "{D}/lidar", "--method", "linear", "--format", "npy", "-o", "{O}"]
    ),
    "accumulate": {
        "old": [
            "accumulate",
            "{S}/velodyne",
            "--calib",
            "{S}/calib",
            "--image-size",
            "1242x375",
            "--icp",
            "--window",
            "1",
            "-o",
            "{O}",
        ],
        "new": [
            "accumulate",
            "{S}/velodyne",
            "--calib",
            "{S}/calib",
            "--image-size",
            "1242x375",
            "--icp",
            "--neighbours",
            "1",
            "-o",
            "{O}",
        ],
    },
    "dataset_build": {
        "old": [
            "dataset",
            "build",
            "--rgb",
            "{S}/image_2",
            "--sparse",
            "{D}/lidar",
            "--gt",
            "{S}/depth_gt",
            "--calib",
            "{S}/calib",
            "--split",
            "0.6,0.2,0.2",
            "-o",
            "{O}",
        ],
        "new": [
            "dataset",
            "build",
            "--rgb",
            "{S}/image_2",
            "--sparse",
            "{D}/lidar",
            "--gt",
            "{S}/depth_gt",
            "--calib",
            "{S}/calib",
            "--splits",
            "0.6,0.2,0.2",
            "-o",
            "{O}",
        ],
    },
    "dataset_export": _same(
        [
            "dataset",
            "export",
            "{D}/raw_lidar",
            "--name",
            "velodyne_raw",
            "--split",
            "train",
            "-o",
            "{O}",
        ],
        real=True,
    ),
    "dataset_kitti_raw": {
        "old": [
            "dataset",
            "kitti-raw",
            "{R}/kitti-raw-sequence-2011_09_26",
            "--beams",
            "4",
            "--split",
            "0.6,0.2,0.2",
            "-o",
            "{O}",
        ],
        "new": [
            "dataset",
            "kitti-raw",
            "{R}/kitti-raw-sequence-2011_09_26",
            "--beams",
            "4",
            "--splits",
            "0.6,0.2,0.2",
            "-o",
            "{O}",
        ],
        "real": True,
    },
}
