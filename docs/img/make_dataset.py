"""Regenerate docs/img/dataset_samples.png: a dataset built from sample_data, read back.

Run: ``.venv/bin/python docs/img/make_dataset.py``. It projects the synthetic sample scans,
builds a dataset with ``dataset build``, reads every sample with ``DatasetReader`` and draws
rgb | sparse LiDAR over rgb | ground truth for each, labelled with id, split and density.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.dataset_reader import DatasetReader
from sparsetools.ops.colormap import colorize_depth, side_by_side
from sparsetools.ops.viz import colorbar, depth_panels, label_panel

ROOT = Path(__file__).resolve().parents[2]
SAMPLE = ROOT / "sample_data" / "synthetic"
IMG = Path(__file__).resolve().parent


def sh(*args) -> str:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    if res.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{res.output}")
    return res.output


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        sh(
            "project",
            SAMPLE / "velodyne",
            "--calib",
            SAMPLE / "calib",
            "--image",
            SAMPLE / "image_2",
            "-o",
            t / "lidar",
            "--format",
            "parquet",
        )
        sh(
            "dataset",
            "build",
            "-o",
            t / "ds",
            "--rgb",
            SAMPLE / "image_2",
            "--sparse",
            t / "lidar",
            "--gt",
            SAMPLE / "depth_gt",
            "--calib",
            t / "lidar" / "calib",
        )
        print(sh("dataset", "info", t / "ds"))
        ds = DatasetReader(t / "ds")
        rows = []
        for s in ds:
            r = ds.row(s["id"])
            sparse = depth_panels(s["rgb"], [s["sparse"]], dilate=1, with_colorbar=False)
            gt = colorize_depth(s["gt"], max_depth=80)
            rows.append(
                side_by_side(
                    [
                        label_panel(s["rgb"], f"{s['id']} ({s['split']})", scale=1.8),
                        label_panel(
                            sparse,
                            f"sparse: {r['n_sparse']} pts, {100 * r['density']:.1f} %",
                            scale=1.8,
                        ),
                        label_panel(gt, "gt", scale=1.8),
                    ],
                    vertical=False,
                )
            )
        grid = side_by_side(rows, vertical=True)
        grid = side_by_side([grid, colorbar(grid.shape[1], max_depth=80)], vertical=True)
        small = cv2.resize(grid, None, fx=0.3, fy=0.3, interpolation=cv2.INTER_AREA)
        out = IMG / "dataset_samples.png"
        cv2.imwrite(
            str(out), np.ascontiguousarray(small[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9]
        )
        print(
            f"{out.relative_to(ROOT)}: {small.shape[1]}x{small.shape[0]}, "
            f"{out.stat().st_size / 1024:.0f} KB"
        )


if __name__ == "__main__":
    main()
