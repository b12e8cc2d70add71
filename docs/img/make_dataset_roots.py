"""Regenerate docs/img/dataset_roots.png: one sample of a dataset built from each root kind.

Run: ``.venv/bin/python docs/img/make_dataset_roots.py`` (needs ../shared/data/real). It builds
a nuScenes v1.0-mini-style tree from the real scene-0061 files (tests/_nuscenes_tree.py) and a
KITTI raw date folder from the real 11-frame sequence, runs ``dataset nuscenes`` and
``dataset kitti-raw`` on them, and draws image | sparse input | ground truth of one sample each.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "data" / "real"
IMG = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT / "tests"))

from _nuscenes_tree import build_tree  # noqa: E402
from sparsetools.cli.main import cli  # noqa: E402
from sparsetools.io.dataset_reader import DatasetReader  # noqa: E402
from sparsetools.ops.colormap import side_by_side  # noqa: E402
from sparsetools.ops.viz import colorbar, depth_panels, label_panel  # noqa: E402


def sh(*args) -> None:
    res = CliRunner().invoke(cli, ["-q", *map(str, args)])
    if res.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{res.output}")
    print(res.output)


def row(ds: Path, title: str, width: int) -> np.ndarray:
    reader = DatasetReader(ds)
    s = next(iter(reader))
    r = reader.row(s["id"])
    sparse = depth_panels(s["rgb"], [s["sparse"]], dilate=2, with_colorbar=False)
    gt = depth_panels(s["rgb"], [s["gt"]], dilate=1, with_colorbar=False)
    # Scaled to the row's width first, then labelled: one text size on every panel.
    panels = [
        cv2.resize(p, (width, round(p.shape[0] * width / p.shape[1])))
        for p in (s["rgb"], sparse, gt)
    ]
    texts = [
        f"{title}: {s['id'].split('/')[0]}/{s['id'].split('/')[-1][:10]}",
        f"{r['source']}: {r['n_sparse']} px ({100 * r['density']:.2f} %)",
        f"ground truth: {r['n_gt']} px",
    ]
    panels = [label_panel(p, t, scale=0.65) for p, t in zip(panels, texts, strict=True)]
    return side_by_side(panels, vertical=False)


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        build_tree(REAL, t / "nuscenes")
        sh("dataset", "nuscenes", t / "nuscenes", "-o", t / "nus", "--sweeps", "1",
           "--resize", "0.5", "--crop", "800x350+0+100")  # fmt: skip
        seq = REAL / "kitti-raw-sequence-2011_09_26"
        date = t / "raw" / "2011_09_26"
        date.mkdir(parents=True)
        for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
            shutil.copy(seq / name, date / name)
        drive = date / "2011_09_26_drive_0001_sync"
        for sub, ext in (("velodyne_points", ".bin"), ("image_02", ".png")):
            (drive / sub / "data").mkdir(parents=True)
            shutil.copy(seq / sub / "data" / f"0000000005{ext}", drive / sub / "data")
        sh("dataset", "kitti-raw", date, "-o", t / "kitti", "--beams", "4")
        grid = side_by_side(
            [row(t / "nus", "nuScenes", 600), row(t / "kitti", "KITTI raw", 600)], vertical=True
        )
        grid = side_by_side([grid, colorbar(grid.shape[1], max_depth=80)], vertical=True)
        small = cv2.resize(grid, None, fx=0.75, fy=0.75, interpolation=cv2.INTER_AREA)
        out = IMG / "dataset_roots.png"
        cv2.imwrite(
            str(out), np.ascontiguousarray(small[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9]
        )
        print(f"{out.relative_to(ROOT)}: {small.shape[1]}x{small.shape[0]}")


if __name__ == "__main__":
    main()
