"""Real night images against ``lowlight`` night versions of real KITTI frames (defaults).

Real: the nuScenes night CAM_FRONT and the two Flare7K night photos of
``../shared/data/real/night-images`` (see its README). Synthetic: ``ops.lowlight.lowlight``
with the default ``LowLightParams`` on the six real KITTI frames of ``../shared/data/real``
(the three depth-benchmark frames with their ground-truth depth and the 2011_09_26 K; the three
object frames with their projected LiDAR depth), four seeds each.

Per image: brightness of the grey image (BT.601 weights, float): mean and percentiles, the
share of pixels below 20 levels, and the noise level in flat dark regions: 16 x 16 patches with
a mean of 8-60 grey levels whose structure (mean gradient magnitude of the image smoothed with
sigma 2) is in the lowest quarter of those dark patches; in each, Immerkaer's estimator
``sigma = sqrt(pi / 2) / (6 (w - 2) (h - 2)) * sum |I * N|``, ``N = [1 -2 1; -2 4 -2; 1 -2 1]``
(insensitive to linear ramps); the median over the patches, in 8-bit grey levels. Then what
``s_b ~ U(0.4, 1.0)`` means: the synthetic mean divided by the day mean.

The patch noise estimator is vectorised; it is checked against (and timed with) a
straightforward per-patch loop on the same image.

Run: ``.venv/bin/python benchmarks/compare_night.py [--picture docs/img/night_compare.png]``
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import compare

ROOT = Path(__file__).resolve().parent.parent
REAL = ROOT.parent / "shared" / "data" / "real"
NIGHT = REAL / "night-images"
P_RECT_02 = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])
PATCH = 16
DARK = (8.0, 60.0)
SEEDS = 4
LAPLACE = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)


def grey(rgb: np.ndarray) -> np.ndarray:
    """BT.601 grey in float64, 8-bit levels (no rounding to integers)."""
    return rgb.astype(np.float64) @ np.array([0.299, 0.587, 0.114])


def _patch_view(a: np.ndarray) -> np.ndarray:
    h, w = (a.shape[0] // PATCH) * PATCH, (a.shape[1] // PATCH) * PATCH
    return a[:h, :w].reshape(h // PATCH, PATCH, w // PATCH, PATCH).swapaxes(1, 2)


def flat_dark_noise(g: np.ndarray) -> tuple[float, int]:
    """(median noise sigma over flat dark patches, number of patches); NaN when none."""
    import cv2

    smooth = cv2.GaussianBlur(g, (0, 0), 2.0)
    gy, gx = np.gradient(smooth)
    structure = _patch_view(np.hypot(gx, gy)).mean(axis=(2, 3))
    means = _patch_view(g).mean(axis=(2, 3))
    # Laplacian response of every pixel; a patch uses the responses of its interior pixels.
    lap = np.abs(cv2.filter2D(g, -1, LAPLACE, borderType=cv2.BORDER_REFLECT))
    inner = _patch_view(lap)[:, :, 1:-1, 1:-1].sum(axis=(2, 3))
    sigma = math.sqrt(math.pi / 2) / (6 * (PATCH - 2) ** 2) * inner
    dark = (means >= DARK[0]) & (means <= DARK[1])
    if not dark.any():
        return math.nan, 0
    flat = dark & (structure <= np.quantile(structure[dark], 0.25))
    return float(np.median(sigma[flat])), int(flat.sum())


def flat_dark_noise_reference(g: np.ndarray) -> tuple[float, int]:
    """The same estimator, patch by patch and pixel by pixel where it is cheap to do so."""
    import cv2

    smooth = cv2.GaussianBlur(g, (0, 0), 2.0)
    gy, gx = np.gradient(smooth)
    grad = np.hypot(gx, gy)
    rows, cols = g.shape[0] // PATCH, g.shape[1] // PATCH
    pad = np.pad(g, 1, mode="symmetric")
    stats = []
    for i in range(rows):
        for j in range(cols):
            y0, x0 = i * PATCH, j * PATCH
            patch = g[y0 : y0 + PATCH, x0 : x0 + PATCH]
            total = 0.0
            for y in range(y0 + 1, y0 + PATCH - 1):
                for x in range(x0 + 1, x0 + PATCH - 1):
                    total += abs(float((pad[y : y + 3, x : x + 3] * LAPLACE).sum()))
            s = math.sqrt(math.pi / 2) / (6 * (PATCH - 2) ** 2) * total
            stats.append((patch.mean(), grad[y0 : y0 + PATCH, x0 : x0 + PATCH].mean(), s))
    dark = [t for t in stats if DARK[0] <= t[0] <= DARK[1]]
    if not dark:
        return math.nan, 0
    cut = float(np.quantile([t[1] for t in dark], 0.25))
    chosen = [t[2] for t in dark if t[1] <= cut]
    return float(np.median(chosen)), len(chosen)


def brightness(g: np.ndarray) -> dict:
    p = np.percentile(g, [5, 50, 95, 99])
    return {"mean": float(g.mean()), "p5": p[0], "p50": p[1], "p95": p[2], "p99": p[3],
            "below20": float((g < 20).mean())}  # fmt: skip


def kitti_frames():
    """(name, rgb, depth, K) of the six real KITTI frames."""
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import image_header_size, read_depth_png, read_image
    from sparsetools.io.kitti import read_velodyne_bin
    from sparsetools.ops.projection import project_points

    gt = REAL / "kitti-depth-gt-metric3d"
    for f in sorted((gt / "rgb").glob("*.png")):
        yield f.stem, read_image(f), read_depth_png(gt / "depth" / f.name), P_RECT_02
    obj = REAL / "kitti-object-kuixu"
    for f in sorted((obj / "image_2").glob("*.png")):
        size = image_header_size(f.read_bytes())
        calib = load_calibration(obj / "calib" / f"{f.stem}.txt", image_size=size)
        depth = project_points(read_velodyne_bin(obj / "velodyne" / f"{f.stem}.bin"), calib)
        yield f"obj{f.stem}", read_image(f), depth, calib.K


def row(name: str, g: np.ndarray) -> dict:
    noise, n = flat_dark_noise(g)
    return {"name": name, **brightness(g), "noise": noise, "patches": n}


def print_table(rows: list[dict]) -> None:
    print("| image | mean | p5 | p50 | p95 | p99 | < 20 | noise sigma (flat dark) | patches |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['name']} | {r['mean']:.1f} | {r['p5']:.1f} | {r['p50']:.1f} | "
              f"{r['p95']:.1f} | {r['p99']:.1f} | {100 * r['below20']:.0f} % | "
              f"{r['noise']:.2f} | {r['patches']} |")  # fmt: skip


def summary(name: str, rows: list[dict]) -> dict:
    keys = ("mean", "p5", "p50", "p95", "p99", "below20", "noise")
    out = {k: float(np.nanmedian([r[k] for r in rows])) for k in keys}
    out.update(name=name, patches=int(sum(r["patches"] for r in rows)))
    return out


def histogram_panel(curves, width=600, height=260) -> np.ndarray:
    """Grey-level histograms (share of pixels per 4-level bin) as lines, drawn with OpenCV."""
    import cv2

    img = np.full((height, width, 3), 255, np.uint8)
    left, bottom, top = 40, height - 30, 10
    hists = [np.histogram(g, bins=64, range=(0, 256))[0] / g.size for _, g, _ in curves]
    peak = max(float(h.max()) for h in hists)
    cv2.line(img, (left, bottom), (width - 10, bottom), (0, 0, 0), 1)
    cv2.line(img, (left, bottom), (left, top), (0, 0, 0), 1)
    for level in (0, 64, 128, 192, 255):
        x = left + int(level / 256 * (width - 10 - left))
        cv2.putText(img, str(level), (x - 8, height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)  # fmt: skip
    for (label, _, colour), h, k in zip(curves, hists, range(len(curves)), strict=True):
        xs = left + (np.arange(64) + 0.5) / 64 * (width - 10 - left)
        ys = bottom - h / peak * (bottom - top)
        pts = np.stack([xs, ys], axis=1).astype(np.int32)
        cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)
        cv2.putText(img, label, (width - 250, 25 + 18 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                    colour, 1, cv2.LINE_AA)  # fmt: skip
    return img


def make_picture(path: Path, real: list, synth: list, synth_grey: np.ndarray) -> None:
    import cv2

    def fit(rgb, label, h=240):
        out = cv2.resize(rgb, (round(rgb.shape[1] * h / rgb.shape[0]), h),
                         interpolation=cv2.INTER_AREA)  # fmt: skip
        for colour, width in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(out, label, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, width,
                        cv2.LINE_AA)  # fmt: skip
        return out

    top = np.concatenate([fit(rgb, f"real: {name}") for name, rgb in real], axis=1)
    bottom = np.concatenate([fit(rgb, f"lowlight: KITTI {name}", 160) for name, rgb in synth[:2]],
                            axis=1)  # fmt: skip
    width = max(top.shape[1], bottom.shape[1])
    pad = lambda a: np.pad(a, ((0, 0), (0, width - a.shape[1]), (0, 0)), constant_values=255)  # noqa: E731
    curves = [(name, grey(rgb), c) for (name, rgb), c in zip(real, [(200, 0, 0), (0, 140, 0),
              (0, 0, 200)], strict=True)]  # fmt: skip
    curves.append(("lowlight defaults (24 KITTI)", synth_grey, (0, 0, 0)))
    hist = histogram_panel(curves, width=width, height=260)
    sheet = np.concatenate([pad(top), pad(bottom), hist], axis=0)
    scale = 1.0
    while True:  # keep the docs picture under 380 KB (noisy images compress badly)
        img = cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        _, buf = cv2.imencode(".png", img[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if len(buf) <= 380 * 1024:
            break
        scale *= 0.9
    path.write_bytes(buf.tobytes())
    sheet = img
    print(f"picture: {path} ({sheet.shape[1]}x{sheet.shape[0]}, {len(buf) // 1024} KB)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--picture", type=Path, help="write the comparison picture (PNG) here")
    args = ap.parse_args()
    if not NIGHT.is_dir():
        sys.exit(f"real night images not present at {NIGHT}")
    from sparsetools.io.image import read_image
    from sparsetools.ops.lowlight import LowLightParams, lowlight
    from sparsetools.random import frame_rng

    print(f"load average (1, 5, 15 min): {os.getloadavg()}, {os.cpu_count()} CPUs")
    real = [("nuScenes night", read_image(NIGHT / "n015-2018-11-21-19-21-35+0800__CAM_FRONT__1542799608112460.jpg")),
            ("Flare7K input1", read_image(NIGHT / "flare7k_input1.png")),
            ("Flare7K input5", read_image(NIGHT / "flare7k_input5.png"))]  # fmt: skip
    real_rows = [row(n, grey(rgb)) for n, rgb in real]
    params = LowLightParams()
    day_rows, night_rows, synth, ratios, s_b = [], [], [], [], []
    pooled = []
    for name, rgb, depth, K in kitti_frames():
        g_day = grey(rgb)
        day_rows.append(row(f"KITTI {name} day", g_day))
        for seed in range(SEEDS):
            # Per-frame streams as lowlight-synth draws them (frame_rng(seed, "<stem>:<k>")).
            rng = frame_rng(0, f"{name}:{seed}")
            night, rec = lowlight(rgb, depth=depth, K=K, rng=rng, params=params)
            g = grey(night)
            night_rows.append(row(f"KITTI {name} seed {seed}", g))
            ratios.append(g.mean() / g_day.mean())
            s_b.append(rec.brightness)
            pooled.append(g.ravel())
            if seed == 0:
                synth.append((name, night))
    print("\nper real night image")
    print_table(real_rows)
    print("\nmedians over images")
    print_table([summary("real night (3)", real_rows), summary("KITTI day (6)", day_rows),
                 summary(f"lowlight defaults ({len(night_rows)})", night_rows)])  # fmt: skip
    ratios, s_b = np.array(ratios), np.array(s_b)
    print(f"\nsynthetic mean / day mean: median {np.median(ratios):.2f}, range "
          f"{ratios.min():.2f}-{ratios.max():.2f}; s_b drawn {s_b.min():.2f}-{s_b.max():.2f}; "
          f"correlation {np.corrcoef(ratios, s_b)[0, 1]:.3f}")  # fmt: skip
    day_mean = float(np.median([r["mean"] for r in day_rows]))
    nu = real_rows[0]["mean"]
    print(f"s_b ~ U(0.4, 1.0): the image is 1 - s_b = 0-60 % darker (median 30 %); the nuScenes "
          f"night mean {nu:.1f} over the KITTI day mean {day_mean:.1f} is s_b = "
          f"{nu / day_mean:.2f}, at the bottom of the range: "
          f"{100 * np.mean(np.array([r['mean'] for r in night_rows]) > nu):.0f} % of the "
          "synthetic images are brighter than it")  # fmt: skip
    g = grey(real[0][1])
    assert flat_dark_noise(g) == flat_dark_noise_reference(g) or np.allclose(
        flat_dark_noise(g), flat_dark_noise_reference(g), rtol=1e-9
    ), "vectorised and per-patch noise estimates differ"
    print()
    compare("flat-dark-patch noise, 1600x900 grey", lambda: flat_dark_noise(g),
            lambda: flat_dark_noise_reference(g), reference_name="per-patch loops", repeat=3)  # fmt: skip
    if args.picture:
        make_picture(args.picture, real, synth, np.concatenate(pooled))


if __name__ == "__main__":
    main()
