"""Pictures and intrinsic-error tables of docs/jbf-expand.md.

Run from the repository root: ``python docs/img/make_jbf.py``. Writes docs/img/jbf_kitti.png
(when ../shared/data/real is present) and docs/img/jbf_synthetic.png, and prints the tables
in Markdown.

- KITTI: the three depth-benchmark frames of ../shared/data/real/kitti-depth-gt-metric3d; the
  "radar" is 60 pixels of the semi-dense ground truth drawn in the horizon band (rows
  150-250) with 0.2 m Gaussian noise (the seeds of tests/test_jbf.py); the reference is the
  ground truth itself.
- Synthetic: ``generate_scene(seed=0, frames=2)``; the radar is the merged 5-sweep radar .pcd
  projected with its calibration; the reference is the dense rendered depth.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from sparsetools.io.calib import load_calibration
from sparsetools.io.image import read_depth_png, read_image
from sparsetools.io.nuscenes import read_radar_pcd
from sparsetools.ops.colormap import overlay_depth, side_by_side
from sparsetools.ops.intrinsic import intrinsic_error, mean_intrinsic_error
from sparsetools.ops.jbf import height_extend, jbf_expand
from sparsetools.ops.projection import project_points
from sparsetools.ops.text import put_outlined_text

HERE = Path(__file__).resolve().parent
REAL = HERE.parent.parent.parent / "shared" / "data" / "real"
KITTI_F = 721.5377  # P_rect_02 of the 2011_09_26 drives (1242x375)
ROWS = ("raw", "height-extend", "jbf", "range", "spatial")
LABELS = {
    "raw": "raw radar",
    "height-extend": "height-extend",
    "jbf": "JBF (25, 10)",
    "range": "range only (-, 10)",
    "spatial": "spatial only (25, -)",
}


def kitti_frames():
    root = REAL / "kitti-depth-gt-metric3d"
    for stem in ("0000000005", "0000000050", "0000000100"):
        gt = read_depth_png(root / "depth" / f"{stem}.png")
        rgb = read_image(root / "rgb" / f"{stem}.png")
        rng = np.random.default_rng(int(stem))
        band = np.zeros(gt.shape, bool)
        band[150:250] = True
        ys, xs = np.nonzero((gt > 0) & band)
        pick = rng.choice(ys.size, 60, replace=False)
        radar = np.zeros_like(gt)
        noise = rng.normal(0, 0.2, pick.size).astype(np.float32)
        radar[ys[pick], xs[pick]] = gt[ys[pick], xs[pick]] + noise
        yield stem, rgb, radar, gt, KITTI_F, KITTI_F


def synthetic_frames(folder: Path):
    from sparsetools.synth import generate_scene

    generate_scene(folder, seed=0, frames=2, underwater_frames=0)
    for stem in ("000000", "000001"):
        calib = load_calibration(folder / "calib_radar" / f"{stem}.json")
        radar = project_points(read_radar_pcd(folder / "radar" / f"{stem}.pcd"), calib)
        rgb = read_image(folder / "image_2" / f"{stem}.png")
        gt = read_depth_png(folder / "depth_gt" / f"{stem}.png")
        yield stem, rgb, radar, gt, calib.fx, calib.fy


def expand_all(rgb, radar, fx, fy) -> dict:
    maps = {"raw": radar, "height-extend": height_extend(radar, fy=fy)}
    for kernel in ("jbf", "range", "spatial"):
        maps[kernel] = jbf_expand(radar, rgb, fx=fx, fy=fy, kernel=kernel)[0]
    return maps


def label(panel: np.ndarray, text: str) -> np.ndarray:
    return put_outlined_text(panel.copy(), text, (8, 24), scale=0.7, thickness=1, outline=2)


def figure(rgb, maps, path: Path, *, scale: float = 0.5) -> None:
    """Figure 7 of the paper: raw radar, JBF, range only, spatial only over the image.

    The image is shown in gray (the depth colours stand out, and the PNG stays small).
    """
    size = (round(rgb.shape[1] * scale), round(rgb.shape[0] * scale))
    gray = np.repeat(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)[:, :, None], 3, axis=2)
    panels = []
    for name in ("raw", "jbf", "range", "spatial"):
        over = overlay_depth(gray, maps[name], max_depth=80.0, dilate=3 if name == "raw" else 0)
        small = cv2.resize(over, size, interpolation=cv2.INTER_AREA)
        panels.append(label(small, LABELS[name]))
    picture = side_by_side(panels, vertical=True)
    ok, buf = cv2.imencode(".png", picture[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    path.write_bytes(buf.tobytes())
    print(f"wrote {path} ({len(buf) // 1024} KB)", file=sys.stderr)


def table(title: str, frames) -> None:
    results = {name: [] for name in ROWS}
    first = None
    for stem, rgb, radar, gt, fx, fy in frames:
        maps = expand_all(rgb, radar, fx, fy)
        if first is None:
            first = (stem, rgb, maps)
        for name in ROWS:
            results[name].append(intrinsic_error(maps[name], gt))
    n = len(results["raw"])
    print(f"\n{title} (mean of {n} frames, ground truth <= 80 m)\n")
    print("| radar format | delta1 | delta2 | RMSE (m) | # points | density (%) | x raw |")
    print("|---|---|---|---|---|---|---|")
    raw_points = mean_intrinsic_error(results["raw"])["points"]
    for name in ROWS:
        e = mean_intrinsic_error(results[name])
        print(
            f"| {LABELS[name]} | {e['delta1']:.2f} | {e['delta2']:.2f} | {e['rmse']:.2f} | "
            f"{e['points']:,.0f} | {e['density_percent']:.2f} | {e['points'] / raw_points:,.0f} |"
        )
    return first


def main() -> None:
    if REAL.is_dir():
        _, rgb, maps = table("KITTI, 60 noisy ground-truth seeds", kitti_frames())
        figure(rgb, maps, HERE / "jbf_kitti.png", scale=0.45)
    else:
        print(f"{REAL} not found: KITTI table and picture skipped", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        _, rgb, maps = table("Synthetic street, 5-sweep radar", synthetic_frames(Path(tmp)))
        figure(rgb, maps, HERE / "jbf_synthetic.png")


if __name__ == "__main__":
    main()
