"""Regenerate docs/img/viz_*.png from the real KITTI frame in sample_data/kitti, and the
contact sheet docs/img/viz_sheet.png from the three synthetic frames in sample_data/synthetic.

Run: ``.venv/bin/python docs/img/make_viz.py`` (uses ``beams``, ``project`` and ``viz``).
The KITTI pictures are downscaled by 0.5 after drawing to stay small; the sheet is drawn at
its final size (``--tile-width``), so its labels are drawn once at the size they are read.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
from click.testing import CliRunner

from sparsetools.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
KITTI = ROOT / "sample_data" / "kitti"
SYNTH = ROOT / "sample_data" / "synthetic"
IMG = Path(__file__).resolve().parent


def sh(*args) -> None:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    if res.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{res.output}")


def shrink(drawn: Path, path: Path, scale: float = 0.5) -> None:
    """Write ``drawn`` (a picture in the temporary folder) to ``path``, scaled by ``scale``:
    the run records of ``viz`` stay in the temporary folder, not in docs/img."""
    img = cv2.imread(str(drawn))
    small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(path), small, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(
        f"{path.relative_to(ROOT)}: {small.shape[1]}x{small.shape[0]}, "
        f"{path.stat().st_size / 1024:.0f} KB"
    )


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        calib = KITTI / "calib"
        image = KITTI / "image_2"
        sh("beams", KITTI / "velodyne", "--n", "4,16", "-o", t / "beams")
        for name, clouds in (
            ("n64", KITTI / "velodyne"),
            ("n16", t / "beams" / "n16"),
            ("n4", t / "beams" / "n4"),
        ):
            sh("project", clouds, "--calib", calib, "--image", image, "-o", t / name)
        sh(
            "viz",
            t / "n64" / "000001.png",
            "--image",
            image / "000001.png",
            "-o",
            t / "viz_overlay.png",
        )
        shrink(t / "viz_overlay.png", IMG / "viz_overlay.png")
        sh(
            "viz",
            "--side-by-side",
            t / "n64" / "000001.png",
            t / "n16" / "000001.png",
            t / "n4" / "000001.png",
            "--image",
            image / "000001.png",
            "--labels",
            "64 beams,16 beams,4 beams",
            "--dilate",
            "3",
            "-o",
            t / "viz_beams.png",
        )
        shrink(t / "viz_beams.png", IMG / "viz_beams.png", 0.45)
        sh("stats", t / "n64" / "000001.png")
        # many frames: a contact sheet of the synthetic street (LiDAR | dense GT per tile)
        sh("project", SYNTH / "velodyne", "--calib", SYNTH / "calib", "--image",
           SYNTH / "image_2", "-o", t / "synth_lidar")  # fmt: skip
        sh("viz", t / "synth_lidar", SYNTH / "depth_gt", "--image", SYNTH / "image_2",
           "--labels", "LiDAR,GT", "--sheet", "--grid", "3x1", "--tile-width", "400",
           "-o", t / "sheets")  # fmt: skip
        shrink(t / "sheets" / "sheet_0001.png", IMG / "viz_sheet.png", 1.0)


if __name__ == "__main__":
    main()
