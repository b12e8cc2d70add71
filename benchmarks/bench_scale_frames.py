"""Cost per frame at dataset scale: time and peak memory of whole commands against N frames.

Run: ``.venv/bin/python benchmarks/bench_scale_frames.py [N ...]`` (default 1000 4000, as
``make bench`` runs it; the table of docs/scale.md: ``1000 4000 16000 64000``, about 15 minutes
and 2.5 GB of temporary files). Not a test.

N tiny frames (2,000 LiDAR points, 64x32 maps, 40 sequences) so that the per-frame
bookkeeping, not the arithmetic, is what is measured (issue 28). For each N, each step runs as
its own process; its wall time and its peak resident memory (``ru_maxrss`` of that child from
``os.wait4``) are printed with the machine's load:

1. ``sparsetools project VELODYNE --calib CALIB --image-size 64x32 -o DEPTH``
2. the same command again (a no-op rerun: every frame up to date)
3. ``sparsetools dataset build -o DS --rgb IMAGES --sparse DEPTH --calib CALIB``
4. ``sparsetools dataset verify DS``

Targets (issue 28): peak memory at 64k frames within 1.5x of the 1k-frame figure for
``project``, the no-op rerun and ``verify``, under 2x for ``dataset build``; time per frame
flat within 20 %.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import load

ROOT = Path(__file__).resolve().parent.parent
#: What ``sparsetools.ops.projection`` switches at (read here so the probe below follows it).
COMPILED_AFTER_POINTS = 80_000_000
NO_SWITCH = (
    "import sys, sparsetools.ops.projection as p; p.COMPILED_AFTER_POINTS = 10**18; "
    "from sparsetools.cli.main import main; sys.argv[0] = 'sparsetools'; main(sys.argv[1:])"
)
SEQUENCES = 40
POINTS = 2000
SIZE = (64, 32)


def _calib_text() -> str:
    fx = 32.0  # a 90-degree field of view over 64 columns
    p = f"{fx} 0 32 0 0 {fx} 16 0 0 0 1 0"
    eye = "1 0 0 0 1 0 0 0 1"
    velo = "0 -1 0 0 0 0 -1 0 1 0 0 0"  # KITTI's axes: x forward -> z
    return (
        f"P0: {p}\nP1: {p}\nP2: {p}\nP3: {p}\nR0_rect: {eye}\nTr_velo_to_cam: {velo}\n"
        f"Tr_imu_to_velo: {velo}\n"
    )


def make_frames(root: Path, n: int) -> tuple[Path, Path, Path]:
    """N clouds and images in SEQUENCES folders; one calibration file."""
    import cv2

    rng = np.random.default_rng(0)
    base = np.column_stack(
        [rng.uniform(2, 40, POINTS), rng.uniform(-30, 30, POINTS), rng.uniform(-2, 1, POINTS),
         rng.uniform(0, 1, POINTS)]
    ).astype(np.float32)  # fmt: skip
    image = rng.integers(0, 255, (SIZE[1], SIZE[0], 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", image)
    assert ok
    png = png.tobytes()
    velo, images = root / "velodyne", root / "image_2"
    jitter = rng.normal(0, 0.01, (n, 1, 1)).astype(np.float32)  # one per frame, broadcast
    for i in range(n):
        seq = f"seq_{i % SEQUENCES:03d}"
        name = f"{i // SEQUENCES:06d}"
        if i < SEQUENCES:
            (velo / seq).mkdir(parents=True)
            (images / seq).mkdir(parents=True)
        (base + jitter[i]).tofile(velo / seq / f"{name}.bin")
        (images / seq / f"{name}.png").write_bytes(png)
    calib = root / "calib.txt"
    calib.write_text(_calib_text())
    return velo, images, calib


def run(cmd: list[str]) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of one child process."""
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd[:3])} failed ({proc.returncode}): {err[-400:]}")
    return wall, usage.ru_maxrss / 1024.0  # kilobytes on Linux


def main(sizes: list[int]) -> None:
    exe = ROOT / ".venv" / "bin" / "sparsetools"
    cli = [str(exe)] if exe.exists() else [sys.executable, "-m", "sparsetools.cli.main"]
    rows = []
    for n in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            root = Path(tmp)
            velo, images, calib = make_frames(root, n)
            depth, ds = root / "depth", root / "ds"
            project = [*cli, "project", str(velo), "--calib", str(calib), "--image-size",
                       f"{SIZE[0]}x{SIZE[1]}", "-o", str(depth), "--quiet"]  # fmt: skip
            steps = {
                "project": project,
                "no-op rerun": project,
                "dataset build": [*cli, "dataset", "build", "-o", str(ds), "--rgb", str(images),
                                  "--sparse", str(depth), "--calib", str(calib), "--quiet"],
                "verify": [*cli, "dataset", "verify", str(ds), "--quiet"],
            }  # fmt: skip
            if n * POINTS > COMPILED_AFTER_POINTS:
                # a probe: the run passes the point count where a process switches to the
                # compiled z-buffer and loads numba (~120 MB); the same run without the switch
                # separates that one-time load from the per-frame bookkeeping
                steps["project, no numba switch"] = [
                    sys.executable, "-c", NO_SWITCH, *project[len(cli) : -3], "-o",
                    str(root / "depth_numpy"),
                    "--quiet"]  # fmt: skip
            row = {"n": n}
            for name, cmd in steps.items():
                before = load()
                wall, rss = run(cmd)
                row[name] = (wall, rss, before)
                print(f"N={n:6d} {name:14s} {wall:8.2f} s  {1e6 * wall / n:7.0f} us/frame  "
                      f"max RSS {rss:6.0f} MB  ({before})", flush=True)  # fmt: skip
            rows.append(row)
            shutil.rmtree(root / "ds", ignore_errors=True)
    print()
    names = [s for s in steps if s in rows[0]]
    print("| N frames | " + " | ".join(f"{s} | its max RSS" for s in names) + " |")
    print("| --- " * (1 + 2 * len(names)) + "|")
    for row in rows:
        cells = [f"{row[s][0]:.2f} s | {row[s][1]:.0f} MB" for s in names]
        print(f"| {row['n']:,} | " + " | ".join(cells) + " |")
    if len(rows) > 1:
        first, last = rows[0], rows[-1]
        for s in names:
            ratio = last[s][1] / first[s][1]
            per = (last[s][0] / last["n"]) / (first[s][0] / first["n"])
            print(f"{s}: max RSS {last['n']:,} / {first['n']:,} frames = {ratio:.2f}x; "
                  f"time per frame {per:.2f}x")  # fmt: skip


if __name__ == "__main__":
    args = [int(a) for a in sys.argv[1:] if a.isdigit()]
    main(args or [1000, 4000])
