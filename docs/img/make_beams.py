"""Regenerate the beams pictures, figures and the HDL-64E sensor profile.

Run from the repository root (needs ../shared/data/real)::

    .venv/bin/python docs/img/make_beams.py            # pictures + figures
    .venv/bin/python docs/img/make_beams.py profile    # src/sparsetools/data/hdl64e_kitti.json

``figures`` prints the numbers quoted in docs/beams.md: the elevation fallback's agreement
with scan order, the horizon lasers per frame, and the density of the projected map per N.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
REAL = ROOT.parent / "shared" / "data" / "real"
KITTI = REAL / "kitti-object-kuixu"
FRAMES = ("000000", "000001", "000002")
PICTURE_FRAME = "000001"
SKY_ROWS = 100


def _load(stem):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import read_image
    from sparsetools.io.pointcloud import read_points

    points = read_points(strict=True, path=KITTI / "velodyne" / f"{stem}.bin")
    image = read_image(KITTI / "image_2" / f"{stem}.png")
    calib = load_calibration(KITTI / "calib" / f"{stem}.txt").with_size(
        image.shape[1], image.shape[0]
    )
    return points, image, calib


def make_profile() -> Path:
    from sparsetools.ops.beams import scan_order_rings
    from sparsetools.ops.lidar_profile import fit_sensor_profile

    clouds, rings = [], []
    for stem in FRAMES:
        points, _, _ = _load(stem)
        ring = scan_order_rings(points, n_lasers=64)
        assert ring[-1] == 63, f"{stem}: scan order did not give 64 rings"
        clouds.append(points)
        rings.append(ring)
    profile = fit_sensor_profile(
        clouds,
        rings,
        n_lasers=64,
        name="hdl64e-kitti",
        source=(
            "Velodyne HDL-64E of the KITTI rig, measured by docs/img/make_beams.py on KITTI "
            "object training frames 000000-000002 (scan-order rings). elevation_deg: median "
            "apparent elevation atan2(z, r) of points with r > 20 m (at least 20 of them), "
            "else the laser's cone at r = 30 m; beam_angle_deg / z_offset_m: least-squares "
            "cone z = r tan(a) + h over all the laser's points."
        ),
    )
    out = ROOT / "src" / "sparsetools" / "data" / "hdl64e_kitti.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(profile.to_dict(), indent=1) + "\n")
    print(f"wrote {out}")
    return out


def make_pictures() -> None:
    from sparsetools.io.sensor_profile import load_sensor_profile
    from sparsetools.ops.beams import recover_rings, select_beams
    from sparsetools.ops.colormap import overlay_depth, side_by_side
    from sparsetools.ops.projection import project_points

    points, image, full = _load(PICTURE_FRAME)
    # Above row 100 is sky that no beam reaches: the pictures crop it (and their intrinsics).
    image = image[SKY_ROWS:]
    calib = full.cropped(SKY_ROWS, 0, image.shape[0], image.shape[1])
    ring = recover_rings(points)
    profile = load_sensor_profile("hdl64e-kitti")
    panels = []
    for n in (1, 2, 4, 16):
        sel = select_beams(points, ring, n=n, profile=profile)
        density = (
            100 * np.count_nonzero(project_points(sel.points, full)) / (full.width * full.height)
        )
        panel = overlay_depth(image, project_points(sel.points, calib), dilate=1)
        panels.append(
            _label(panel, f"{n} beam{'s' if n > 1 else ''} ({sel.select}): {density:.2f} % pixels")
        )
    # Half resolution keeps the PNG small; dilation before resizing keeps points visible.
    import cv2

    grid = side_by_side(panels, vertical=True)
    grid = cv2.resize(grid, (grid.shape[1] // 2, grid.shape[0] // 2), interpolation=cv2.INTER_AREA)
    _save(ROOT / "docs" / "img" / "beams_1_2_4_16.png", grid)

    # Published pl++ 4-beam vs horizon 4-beam on the same frame.
    pl = select_beams(points, n=4, select="pl++", calib=full)  # the published full-image FOV
    hz = select_beams(points, ring, n=4, profile=profile)
    panels = []
    for name, sel in (("horizon, 4 lasers", hz), ("pl++ 4 bins", pl)):
        lasers = np.unique(ring[sel.index]).size
        depth = project_points(sel.points, calib)
        panels.append(
            _label(overlay_depth(image, depth, dilate=1), f"{name}: {lasers} physical lasers")
        )
    grid = side_by_side(panels, vertical=True)
    grid = cv2.resize(grid, (grid.shape[1] // 2, grid.shape[0] // 2), interpolation=cv2.INTER_AREA)
    _save(ROOT / "docs" / "img" / "beams_horizon_vs_plpp.png", grid)


def _save(path: Path, rgb: np.ndarray, limit_kb: int = 390) -> None:
    """PNG at maximum compression, scaled down until it is under ``limit_kb``."""
    import cv2

    while True:
        ok, buf = cv2.imencode(".png", rgb[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        assert ok
        if buf.size <= limit_kb * 1024:
            break
        size = (int(rgb.shape[1] * 0.9), int(rgb.shape[0] * 0.9))
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
    path.write_bytes(buf.tobytes())
    print(f"wrote {path} ({buf.size // 1024} KB, {rgb.shape[1]}x{rgb.shape[0]})")


def _label(panel: np.ndarray, text: str) -> np.ndarray:
    from sparsetools.ops.text import put_outlined_text

    return put_outlined_text(panel.copy(), text, (10, 36), scale=1.1, thickness=2, outline=2)


def figures() -> None:
    from sparsetools.io.sensor_profile import load_sensor_profile
    from sparsetools.ops.beams import (
        elevation_rings,
        horizon_rings,
        recover_rings,
        ring_elevations,
        select_beams,
    )
    from sparsetools.ops.projection import project_points

    profile = load_sensor_profile("hdl64e-kitti")
    rng = np.random.default_rng(0)
    print("elevation fallback vs scan order (fraction of points with the same ring)")
    for stem in FRAMES:
        points, _, calib = _load(stem)
        ring = recover_rings(points)
        az = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        perm = rng.permutation(points.shape[0])
        cases = {
            "full": np.arange(points.shape[0]),
            "shuffled": perm,
            "front 90 deg": np.flatnonzero(np.abs(az) < 45),
            "10 % random": np.flatnonzero(rng.random(points.shape[0]) < 0.1),
        }
        for name, idx in cases.items():
            generic = np.mean(elevation_rings(points[idx]) == ring[idx])
            prof = np.mean(elevation_rings(points[idx], profile=profile) == ring[idx])
            print(
                f"  {stem} {name:<13} generic {100 * generic:8.4f} %  profile {100 * prof:8.4f} %"
            )
        far = horizon_rings(ring_elevations(points, ring), 4)
        print(
            f"  {stem} horizon lasers: profile {horizon_rings(profile.elevation_deg, 4)}, "
            f"this frame's far points {far}"
        )
        dens = {}
        for n in (1, 2, 3, 4, 8, 16, 32):
            sel = select_beams(points, ring, n=n, profile=profile)
            depth = project_points(sel.points, calib)
            dens[n] = 100 * np.count_nonzero(depth) / depth.size
        pl = select_beams(points, n=4, select="pl++", calib=calib)
        depth_pl = project_points(pl.points, calib)
        full = project_points(points, calib)
        print(
            f"  {stem} density %: "
            + ", ".join(f"N={n}: {d:.3f}" for n, d in dens.items())
            + f", pl++ 4: {100 * np.count_nonzero(depth_pl) / depth_pl.size:.3f}"
            + f" ({np.unique(ring[pl.index]).size} lasers)"
            + f", all 64: {100 * np.count_nonzero(full) / full.size:.3f}"
        )


if __name__ == "__main__":
    what = sys.argv[1:] or ["pictures", "figures"]
    if "profile" in what:
        make_profile()
    if "pictures" in what:
        make_pictures()
    if "figures" in what:
        figures()
