"""Regenerate the pictures of docs/synth-scene.md with the project itself.

Run from the repository root: ``.venv/bin/python docs/img/make_synth_scene.py [--out DIR]``.

- ``synth-scene.png``: frame 0 of the street scene of seed 0 (``sample_data/synthetic``'s
  000000), simulated: the camera image over its exact depth, 0-80 m in turbo, black where there is no
  truth (the sky).
- ``synth_video_strip.png``: frames 0, 10 and 20 of video seed 0 (416x128): image, moving
  objects tinted red, true depth.
- ``synth_video_seeds.png``: frame 0 of video seeds 0-7.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent


def turbo(depth: np.ndarray) -> np.ndarray:
    """Depth (m) -> RGB, 0-80 m in OpenCV's turbo, black where there is no value."""
    idx = np.clip(np.rint(depth / 80.0 * 255.0), 0, 255).astype(np.uint8)
    rgb = cv2.applyColorMap(idx, cv2.COLORMAP_TURBO)[:, :, ::-1].copy()
    rgb[depth == 0] = 0
    return rgb


def save(path: Path, rgb: np.ndarray) -> None:
    cv2.imwrite(str(path), np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"{path.name}: {rgb.shape[1]}x{rgb.shape[0]}, {path.stat().st_size // 1024} KB")


def scene(out: Path) -> None:
    from sparsetools.synth import Rig, simulate_frame

    f = simulate_frame(0, 0, rig=Rig.kitti())  # frame 000000 of sample_data/synthetic
    save(out / "synth-scene.png", np.vstack([f.image, turbo(f.depth)]))


def video(out: Path) -> None:
    from sparsetools.synth import VideoSimulator, simulate_video

    seq = simulate_video(0, n_frames=21, image_size=(416, 128), lidar=False)
    rows = []
    for k in (0, 10, 20):
        f = seq.frames[k]
        tint = f.image.copy()
        tint[f.moving_mask] = (0.4 * tint[f.moving_mask] + [153, 0, 0]).astype(np.uint8)
        rows.append(np.hstack([f.image, tint, turbo(f.depth)]))
    save(out / "synth_video_strip.png", np.vstack(rows))
    tiles = [
        VideoSimulator(s, 0, n_frames=1, image_size=(416, 128), lidar=False).frame(0).image
        for s in range(8)
    ]
    save(
        out / "synth_video_seeds.png",
        np.vstack([np.hstack(tiles[i : i + 2]) for i in (0, 2, 4, 6)]),
    )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=HERE)
    args = ap.parse_args()
    scene(args.out)
    video(args.out)
