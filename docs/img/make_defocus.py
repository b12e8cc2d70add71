"""Regenerate the pictures of docs/defocus-synth.md and docs/dark-channel.md.

Run from the repository root: ``.venv/bin/python docs/img/make_defocus.py``. Input: the real
KITTI depth-benchmark frame 0000000050 of ``../shared/data/real/kitti-depth-gt-metric3d``
(KITTI, CC BY-NC-SA 3.0) with its semi-dense ground truth, holes filled for the picture: every
pixel without ground truth takes the depth of the nearest pixel with one (Euclidean distance
transform), except above the topmost ground-truth pixel of its column (sky, trees), which is
left empty and rendered as infinitely far (``missing="far"``).

- ``defocus_kitti.png``: sharp image, filled depth, radius map, defocused image (f = 50 mm,
  F/2, 4.65 um pixels, focused at 26 m, disk kernel).
- ``defocus_crop.png``: a crop at a near car's edge, magnified 2x: sharp, the layered composite,
  and a naive per-pixel blur (each pixel takes the blur of its own radius), which leaves the
  background sharp right up to the near object.
- ``dark_channel_kitti.png``: dark channel, the two LDDCV channels and the mask, for the sharp
  and the defocused image.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from sparsetools.io.image import read_depth_png, read_image
from sparsetools.ops.colormap import colorize_depth, side_by_side
from sparsetools.ops.dark_channel import dark_channel_features
from sparsetools.ops.defocus import CameraOptics, DefocusParams, blur_kernel, defocus
from sparsetools.ops.viz import label_panel

HERE = Path(__file__).resolve().parent
GT = HERE.parent.parent.parent / "shared" / "data" / "real" / "kitti-depth-gt-metric3d"
OPTICS = CameraOptics("50mm-f2", 50e-3, 2.0, 4.65e-6, "illustration")
FOCUS_M = 26.0
PARAMS = DefocusParams(camera=OPTICS, focus_distance=(FOCUS_M, FOCUS_M), missing="far")


def save(name: str, rgb: np.ndarray, *, max_kb: int = 380) -> None:
    """PNG at the highest zlib level, scaled down until it fits the size budget."""
    scale = 1.0
    while True:
        img = rgb if scale == 1.0 else cv2.resize(rgb, None, fx=scale, fy=scale,
                                                  interpolation=cv2.INTER_AREA)  # fmt: skip
        ok, buf = cv2.imencode(".png", img[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if ok and len(buf) <= max_kb * 1024:
            break
        scale *= 0.85
    (HERE / name).write_bytes(buf.tobytes())
    print(f"{name}: {img.shape[1]}x{img.shape[0]}, {len(buf) // 1024} KB")


def filled_depth(depth: np.ndarray) -> np.ndarray:
    valid = depth > 0
    _, (iy, ix) = ndimage.distance_transform_edt(~valid, return_indices=True)
    out = depth[iy, ix]
    top = np.where(valid.any(axis=0), valid.argmax(axis=0), depth.shape[0])
    out[np.arange(depth.shape[0])[:, None] < top[None, :]] = 0.0  # above the GT: far
    return out


def radius_colour(radius: np.ndarray, r_max: float) -> np.ndarray:
    t = np.round(np.clip(radius / r_max, 0, 1) * 255).astype(np.uint8)
    return cv2.applyColorMap(t, cv2.COLORMAP_VIRIDIS)[:, :, ::-1].copy()


def naive_blur(image: np.ndarray, radius: np.ndarray, step: float) -> np.ndarray:
    """Each pixel takes its own radius' blur of the whole image (no layers, no occlusion)."""
    layer = np.rint(radius / step).astype(int)
    out = np.empty(image.shape, np.float32)
    img = image.astype(np.float32)
    for k in np.unique(layer):
        kern = blur_kernel(k * step)
        blurred = cv2.filter2D(img, -1, kern, borderType=cv2.BORDER_REFLECT)
        out[layer == k] = blurred[layer == k]
    return np.rint(out).astype(np.uint8)


def gray_panel(x: np.ndarray, vmax: float) -> np.ndarray:
    g = np.round(np.clip(x / vmax, 0, 1) * 255).astype(np.uint8)
    return np.repeat(g[:, :, None], 3, axis=2)


def main() -> None:
    if not GT.is_dir():
        sys.exit(f"real KITTI ground truth not present at {GT}")
    rgb = read_image(GT / "rgb" / "0000000050.png")
    depth = filled_depth(read_depth_png(GT / "depth" / "0000000050.png"))
    blurred, radius, rec = defocus(rgb, depth, params=PARAMS)
    r_max = float(radius.max())
    print(f"radius {radius.min():.2f}-{r_max:.2f} px, r(inf) = {rec.radius_scale:.2f} px")
    top = 90  # the rows above hold sky only
    panels = [
        label_panel(rgb[top:], "sharp (KITTI 0000000050)", scale=0.8),
        label_panel(colorize_depth(depth)[top:], "GT depth, holes filled (black: far)", scale=0.8),
        label_panel(radius_colour(radius, r_max)[top:], f"blur radius 0-{r_max:.1f} px", scale=0.8),
        label_panel(blurred[top:], f"f 50 mm, F/2, 4.65 um, focus {FOCUS_M:g} m", scale=0.8),
    ]
    grid = side_by_side([side_by_side(panels[:2], vertical=False),
                         side_by_side(panels[2:], vertical=False)])  # fmt: skip
    save("defocus_kitti.png", grid)
    naive = naive_blur(rgb, radius, PARAMS.layer_step)
    y0, x0, h, w = 170, 110, 110, 160  # the near car's rear edge against the focused houses
    crop = []
    for a, t in ((rgb, "sharp"), (blurred, "layered (ours)"), (naive, "per-pixel radius")):
        big = cv2.resize(a[y0 : y0 + h, x0 : x0 + w], (2 * w, 2 * h),
                         interpolation=cv2.INTER_NEAREST)  # fmt: skip
        crop.append(label_panel(big, t, scale=0.5))
    save("defocus_crop.png", side_by_side(crop, vertical=False))
    columns = []
    for img, name in ((rgb, "sharp"), (blurred, "defocused")):
        f = dark_channel_features(img)
        columns.append(side_by_side([
            label_panel(gray_panel(f.dark, 1.0)[top:], f"{name}: dark channel (15x15)", scale=1.0),
            label_panel(gray_panel(f.lddcv[..., 0], 0.2)[top:], "LDDCV intensity (0-0.2)",
                        scale=1.0),
            label_panel(gray_panel(f.lddcv[..., 1], 0.2)[top:], "LDDCV dark channel (0-0.2)",
                        scale=1.0),
            label_panel(gray_panel(f.mask.astype(np.float32), 1.0)[top:],
                        f"mask |LDDCV| > 0.05: {100 * f.mask.mean():.1f} %", scale=1.0),
        ]))  # fmt: skip
        print(f"{name}: mask {100 * f.mask.mean():.1f} % of pixels, mean LDDCV "
              f"{f.lddcv[..., 0].mean():.4f} / {f.lddcv[..., 1].mean():.4f}")  # fmt: skip
    save("dark_channel_kitti.png", side_by_side(columns, vertical=False))


if __name__ == "__main__":
    main()
