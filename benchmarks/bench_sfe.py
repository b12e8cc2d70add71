"""EffisDepth SFE (sparse convolutions) against a dense LiDAR branch of the same widths.

Run: ``.venv/bin/python benchmarks/bench_sfe.py`` (about 2-3 minutes on 2 loaded cores);
``--big`` adds the 1216x352 maps, ``--plot docs/img/sfe_density.png`` draws the density curve.

1. Real KITTI maps: the three HDL-64E scans of ../shared/data/real/kitti-object-kuixu, 4 or
   16 rings kept (``sparsetools.recover_rings`` + ``select_beams``, horizon / uniform
   selection), projected with ``project_points`` into 640x192 (the image resized by
   640/1242, bottom 192 rows) and, with ``--big``, 1216x352 (KITTI depth-completion crop: bottom
   352 rows, centre 1216 columns); batch of 4 (the three frames + 000001 mirrored). Without the
   real data, row-structured synthetic maps of the same densities stand in.
2. For each map and three sizes (``small``: SMALL_WIDTHS; ``unet8``: the U-Net's encoder at
   ``--width 8``, scales 1-16; ``paper``: the reconstructed 1.4 M-parameter SFE, scales 1-32):
   forward + backward (training mode, sum of all outputs as the loss), median of ``--repeat``
   runs after one warm-up, of :class:`SparseFeatureExtractor` ("ours") and
   :class:`DenseLidarEncoder` ("reference": the same layers as ``nn.Conv2d``; same parameter
   count, same output shapes).
3. Peak memory: the growth of the resident set (VmHWM after resetting it through
   ``/proc/self/clear_refs``, minus VmRSS before) during the first forward + backward in a fresh
   spawned process per encoder and map. tracemalloc does not see torch's CPU allocations.
4. Time against density (0.1 % .. 30 % valid pixels, row-structured synthetic maps, 640x192,
   batch 4, paper-sized): where the dense branch wins.

Threads: ``--threads 1`` by default. On a machine shared with other jobs two OpenMP threads
wait for each other whenever one is descheduled and timings scatter by 10x; one thread per
process is what a loaded machine can measure reproducibly (``--threads 2`` when idle).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import median_seconds

ROOT = Path(__file__).resolve().parent.parent
KITTI = ROOT.parent / "shared" / "data" / "real" / "kitti-object-kuixu"
FRAMES = ("000000", "000001", "000002")
SIZES = {"640x192": (640, 192), "1216x352": (1216, 352)}
CURVE_DENSITIES = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3)
#: Beam points fill about this fraction of a beam's pixels (4-beam KITTI at 640 px: 0.6-0.7).
ROW_FILL = 0.65


def encoder_options(name: str) -> dict:
    from sparsetools.train.sfe import (
        PAPER_SCALES,
        PAPER_WIDTHS,
        SMALL_WIDTHS,
        UNET_SCALES,
        unet_encoder_widths,
    )

    return {
        "small": {"widths": SMALL_WIDTHS, "scales": PAPER_SCALES},
        "unet8": {"widths": unet_encoder_widths(8), "scales": UNET_SCALES},
        "paper": {"widths": PAPER_WIDTHS, "scales": PAPER_SCALES},
    }[name]


def build(kind: str, name: str):
    import torch

    from sparsetools.train.sfe import DenseLidarEncoder, SparseFeatureExtractor

    torch.manual_seed(0)
    cls = SparseFeatureExtractor if kind == "sfe" else DenseLidarEncoder
    return cls(**encoder_options(name)).train()


def step(model, depth) -> None:
    """One training step's forward + backward (sum of every output as the loss)."""
    model.zero_grad(set_to_none=True)
    sum(o.sum() for o in model(depth)).backward()


# -- input maps ---------------------------------------------------------------------------------
def kitti_maps(n_beams: int, size: tuple[int, int]) -> np.ndarray:
    """(4, 1, H, W) float32 metres: frames 000000-000002 and 000001 mirrored."""
    import sparsetools as st

    W, H = size
    maps = []
    for stem in FRAMES:
        points = st.read_points(KITTI / "velodyne" / f"{stem}.bin")
        calib = st.load_calibration(KITTI / "calib" / f"{stem}.txt")
        w0, h0 = (1224, 370) if stem == "000000" else (1242, 375)
        calib = calib.with_size(w0, h0)
        beams = st.select_beams(points, st.recover_rings(points), n=n_beams).points
        if size == (640, 192):
            c = calib.resized(W / w0)
            c = c.cropped(c.height - H, 0, H, W)
        else:
            c = calib.cropped(h0 - H, (w0 - W) // 2, H, W)
        maps.append(st.project_points(beams, c))
    maps.append(maps[1][:, ::-1])
    return np.ascontiguousarray(np.stack(maps)[:, None])


def row_structured_maps(rng: np.random.Generator, density: float, size, batch=4) -> np.ndarray:
    """Synthetic LiDAR-like maps: wavy rows (beams) in the lower 70 % of the image.

    ``round(density * H / ROW_FILL)`` beams (at least 1, at most one per row of the region),
    each pixel of a beam kept with probability ``density * H / beams`` (about ``ROW_FILL``).
    Beams wave by up to 2 rows when at least 5 rows apart (straight otherwise, so they never
    cross). Depth uniform in [2, 80] m. The tables print the measured density.
    """
    W, H = size
    top = int(0.3 * H)
    rows_available = H - top
    n_rows = min(max(1, round(density * H / ROW_FILL)), rows_available)
    fill = min(1.0, density * H / n_rows)
    out = np.zeros((batch, 1, H, W), np.float32)
    x = np.arange(W)
    for b in range(batch):
        base = np.linspace(top, H - 1, n_rows).round().astype(int)
        phase = rng.uniform(0, 2 * np.pi, n_rows)
        amplitude = 1.5 if rows_available >= 5 * n_rows else 0.0  # beams must not cross
        wobble = np.sin(2 * np.pi * x[None, :] / W + phase[:, None])
        wobble = np.round(amplitude * wobble).astype(int)
        y = np.clip(base[:, None] + wobble, 0, H - 1)
        keep = rng.random(y.shape) < fill
        xx = np.broadcast_to(x, y.shape)
        out[b, 0, y[keep], xx[keep]] = rng.uniform(2, 80, int(keep.sum())).astype(np.float32)
    return out


# -- measurements ---------------------------------------------------------------------------------
def _status_kb() -> dict[str, int]:
    values = {}
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(("VmRSS:", "VmHWM:")):
                key, value = line.split(":")
                values[key] = int(value.split()[0])
    return values


def _peak_child(kind: str, name: str, depth: np.ndarray, threads: int) -> float:
    import torch

    torch.set_num_threads(threads)
    model = build(kind, name)
    d = torch.from_numpy(depth)
    before = _status_kb()["VmRSS"]
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # reset the high-water mark to the current RSS
    except OSError:
        pass  # then VmHWM includes start-up: an upper bound
    step(model, d)
    return (_status_kb()["VmHWM"] - before) / 1024.0


def peak_mb(kind: str, name: str, depth: np.ndarray, threads: int) -> float:
    """Peak RSS growth (MiB) of the first forward + backward in a fresh process."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "depth.npy"
        np.save(path, depth)
        cmd = [sys.executable, __file__, "--peak-child", kind, name, str(path), str(threads)]
        done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return float(done.stdout.split()[-1])


def time_pair_ms(name: str, depth: np.ndarray, repeat: int) -> tuple[float, float]:
    """Median forward + backward ms of the SFE and of the dense twin, runs interleaved.

    Alternating the two (after one warm-up each) exposes both to the same background load,
    so their ratio stays meaningful on a shared machine even when the load drifts.
    """
    import torch

    d = torch.from_numpy(depth)
    models = (build("sfe", name), build("dense", name))
    times: tuple[list[float], list[float]] = ([], [])
    for model in models:
        step(model, d)
    for _ in range(repeat):
        for model, out in zip(models, times, strict=True):
            out.append(1e3 * median_seconds(lambda m=model: step(m, d), repeat=1, warmup=0))
    return statistics.median(times[0]), statistics.median(times[1])


def load() -> str:
    return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def run_maps(args) -> list[dict]:
    rows = []
    real = KITTI.is_dir()
    print(f"maps: {'real KITTI object frames ' + ', '.join(FRAMES) if real else 'synthetic'}")
    sizes = ["640x192", "1216x352"] if args.big else ["640x192"]
    print(
        f"{'map':<22}{'encoder':<8}{'density':>8}{'sites':>7} | {'SFE ms':>8} {'dense ms':>9} "
        f"{'ratio':>6} | {'SFE MiB':>8} {'dense MiB':>9} {'ratio':>6}"
    )
    for size_name in sizes:
        for beams in (4, 16):
            if real:
                depth = kitti_maps(beams, SIZES[size_name])
            else:
                density = 0.0135 if beams == 4 else 0.04
                if size_name == "1216x352":
                    density /= 3.4
                depth = row_structured_maps(np.random.default_rng(beams), density, SIZES[size_name])
            valid = depth > 0
            for name in args.encoders:
                t_s, t_d = time_pair_ms(name, depth, args.repeat)
                m_s = m_d = float("nan")
                if not args.no_memory:
                    m_s = peak_mb("sfe", name, depth, args.threads)
                    m_d = peak_mb("dense", name, depth, args.threads)
                row = {
                    "map": f"{size_name} {beams}-beam",
                    "encoder": name,
                    "density": 100 * valid.mean(),
                    "sites": int(valid.sum()),
                    "sfe_ms": t_s,
                    "dense_ms": t_d,
                    "sfe_mib": m_s,
                    "dense_mib": m_d,
                }
                rows.append(row)
                print(
                    f"{row['map']:<22}{name:<8}{row['density']:>7.2f}%{row['sites']:>7} | "
                    f"{t_s:>8.1f} {t_d:>9.1f} {t_d / t_s:>5.1f}x | "
                    f"{m_s:>8.1f} {m_d:>9.1f} {m_d / m_s:>5.1f}x",
                    flush=True,
                )
    return rows


def run_curve(args) -> list[tuple[float, float, float]]:
    size = SIZES["640x192"]
    print(f"\ntime vs density: 640x192, batch 4, {args.curve_encoder}, row-structured maps")
    print(f"{'density':>9}{'sites':>8} | {'SFE ms':>8} {'dense ms':>9} {'dense/SFE':>10}")
    rng = np.random.default_rng(0)
    curve = []
    for target in CURVE_DENSITIES:
        depth = row_structured_maps(rng, target, size)
        valid = depth > 0
        t_s, t_d = time_pair_ms(args.curve_encoder, depth, args.curve_repeat)
        curve.append((100 * valid.mean(), t_s, t_d))
        print(
            f"{100 * valid.mean():>8.2f}%{int(valid.sum()):>8} | {t_s:>8.1f} {t_d:>9.1f} "
            f"{t_d / t_s:>9.2f}x",
            flush=True,
        )
    return curve


def plot_curve(path: str, curve, title: str) -> None:
    """Log-log time against density, drawn with OpenCV (no plotting library in the project)."""
    import cv2

    w, h, left, right, top, bottom = 720, 420, 80, 30, 40, 60
    img = np.full((h, w, 3), 255, np.uint8)
    dens = np.log10([c[0] for c in curve])
    times = np.log10([t for c in curve for t in c[1:]])
    x0, x1 = np.floor(dens.min()), np.ceil(dens.max())
    y0, y1 = np.floor(times.min()), np.ceil(times.max())

    def px(d, t):
        u = left + (d - x0) / (x1 - x0) * (w - left - right)
        v = h - bottom - (t - y0) / (y1 - y0) * (h - top - bottom)
        return int(round(u)), int(round(v))

    grey, black = (200, 200, 200), (0, 0, 0)
    for e in np.arange(x0, x1 + 1):
        cv2.line(img, px(e, y0), px(e, y1), grey, 1)
        u, v = px(e, y0)
        cv2.putText(img, f"{10**e:g}%", (u - 20, v + 22), 0, 0.45, black, 1, cv2.LINE_AA)
    for e in np.arange(y0, y1 + 1):
        cv2.line(img, px(x0, e), px(x1, e), grey, 1)
        u, v = px(x0, e)
        cv2.putText(img, f"{10**e:g} ms", (u - 75, v + 5), 0, 0.45, black, 1, cv2.LINE_AA)
    for col, colour, label in ((1, (200, 80, 0), "SFE (sparse)"), (2, (0, 0, 200), "dense")):
        pts = [px(np.log10(c[0]), np.log10(c[col])) for c in curve]
        cv2.polylines(img, [np.array(pts, np.int32)], False, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
        y_label = 60 if col == 1 else 80
        cv2.line(img, (w - 200, y_label - 5), (w - 170, y_label - 5), colour, 2)
        cv2.putText(img, label, (w - 160, y_label), 0, 0.5, colour, 1, cv2.LINE_AA)
    cv2.putText(img, title, (left, 25), 0, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, "valid pixels", (w // 2 - 40, h - 12), 0, 0.5, black, 1, cv2.LINE_AA)
    cv2.imwrite(path, img)
    print(f"wrote {path}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--big", action="store_true", help="also 1216x352 maps")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--curve-repeat", type=int, default=3)
    parser.add_argument("--encoders", nargs="+", default=["small", "unet8", "paper"])
    parser.add_argument("--curve-encoder", default="paper")
    parser.add_argument("--no-memory", action="store_true", help="skip the peak-RSS processes")
    parser.add_argument("--no-curve", action="store_true")
    parser.add_argument("--no-maps", action="store_true", help="only the density curve")
    parser.add_argument("--plot", help="write the time-vs-density picture here (PNG)")
    args = parser.parse_args(argv)

    import torch

    from sparsetools.train.sfe import count_parameters

    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s), {os.cpu_count()} CPUs")
    print(f"start: {load()}")
    for name in args.encoders:
        print(
            f"{name:<6} widths {encoder_options(name)['widths']}, "
            f"{count_parameters(build('sfe', name)):,} parameters (both encoders)"
        )
    if not args.no_maps:
        run_maps(args)
    if not args.no_curve:
        curve = run_curve(args)
        if args.plot:
            plot_curve(
                args.plot,
                curve,
                f"forward+backward, 640x192, batch 4, {args.curve_encoder} widths, "
                f"{args.threads} thread(s)",
            )
    print(f"end: {load()}")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--peak-child"]:
        kind, name, path, threads = sys.argv[2:6]
        print(_peak_child(kind, name, np.load(path), int(threads)))
    else:  # under benchmarks/run_all.py the arguments are run_all's
        main(sys.argv[1:] if Path(sys.argv[0]).name == Path(__file__).name else [])
