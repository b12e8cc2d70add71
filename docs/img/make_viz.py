"""Regenerate docs/img/viz_*.png from the real KITTI frame in sample_data/kitti.

Run: ``.venv/bin/python docs/img/make_viz.py`` (uses ``beams``, ``project`` and ``viz``).
The pictures are downscaled by 0.5 after drawing to stay small.
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
IMG = Path(__file__).resolve().parent


def sh(*args) -> None:
    res = CliRunner().invoke(cli, [str(a) for a in args])
    if res.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{res.output}")


def shrink(path: Path, scale: float = 0.5) -> None:
    img = cv2.imread(str(path))
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
            IMG / "viz_overlay.png",
            "--overwrite",
        )
        shrink(IMG / "viz_overlay.png")
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
            IMG / "viz_beams.png",
            "--overwrite",
        )
        shrink(IMG / "viz_beams.png", 0.45)
        sh("stats", t / "n64" / "000001.png")


if __name__ == "__main__":
    main()
