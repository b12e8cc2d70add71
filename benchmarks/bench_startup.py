"""A 1-frame ``project`` run, process start to exit, and what its start-up imports.

Run: ``.venv/bin/python benchmarks/bench_startup.py`` (``make bench`` runs it with the others).

Ours: ``sparsetools -q project FRAME.bin --calib CALIB --image-size 1242x375 -o OUT`` on a real
KITTI frame (a synthetic one when ../shared/data/real is absent). Reference: a minimal Python
script doing the same work in a fresh interpreter (``np.fromfile``,
``sparsetools.ops.projection.project_points``, ``cv2.imwrite``), so the ratio is what the
command line, the frame runner and the provenance record add to the start-up a user cannot
avoid (Python, numpy, OpenCV). Goal (issue 18): at most 0.45 s on an idle machine. Both run in
alternating order with bytecode caches on, as in a user's shell. Then ``python -X importtime``
of the command: the heaviest imports, and the heavy libraries it must not load (numba, torch,
sympy, open3d, pyarrow, scipy).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load

ROOT = Path(__file__).resolve().parent.parent
REAL = ROOT.parent / "shared" / "data" / "real" / "kitti-object-kuixu"
GOAL_S = 0.45
HEAVY = ("numba", "torch", "sympy", "open3d", "pyarrow", "scipy", "dask")

_MINIMAL = """
import sys
import cv2
import numpy as np
from sparsetools.io.calib import load_calibration
from sparsetools.ops.projection import project_points
calib = load_calibration(sys.argv[2], image_size=(1242, 375))
depth = project_points(np.fromfile(sys.argv[1], dtype=np.float32).reshape(-1, 4), calib)
cv2.imwrite(sys.argv[3], np.clip(np.rint(depth.astype(np.float64) * 256), 0, 65535).astype(np.uint16))
"""


def env() -> dict:
    e = dict(os.environ)
    e.pop("PYTHONDONTWRITEBYTECODE", None)  # this sandbox turns bytecode caches off
    return e


def frame(tmp: Path) -> tuple[Path, Path]:
    if REAL.is_dir():
        return REAL / "velodyne" / "000001.bin", REAL / "calib" / "000001.txt"
    from sparsetools.synth import generate_scene

    generate_scene(tmp / "scene", frames=1, underwater_frames=0)
    return tmp / "scene" / "velodyne" / "000000.bin", tmp / "scene" / "calib" / "000000.txt"


def main() -> None:
    exe = ROOT / ".venv" / "bin" / "sparsetools"
    cli = [str(exe)] if exe.exists() else [sys.executable, "-m", "sparsetools.cli.main"]
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        tmp = Path(tmp)
        cloud, calib = frame(tmp)
        runs = iter(range(10**6))

        def ours():
            out = tmp / f"out{next(runs)}"
            subprocess.run([*cli, "-q", "project", str(cloud), "--calib", str(calib),
                            "--image-size", "1242x375", "-o", str(out)],
                           check=True, env=env(), stdout=subprocess.DEVNULL)  # fmt: skip

        def minimal():
            out = tmp / f"min{next(runs)}.png"
            subprocess.run([sys.executable, "-c", _MINIMAL, str(cloud), str(calib), str(out)],
                           check=True, env=env())  # fmt: skip

        t = interleaved({"ours": ours, "minimal": minimal}, repeat=9, warmup=2)
        verdict = "met" if t["ours"] <= GOAL_S else "NOT met"
        print(
            f"1-frame project, process start to exit: ours {t['ours']:.3f} s | minimal script "
            f"{t['minimal']:.3f} s | ratio {t['minimal'] / t['ours']:.2f}x | goal <= {GOAL_S} s: "
            f"{verdict} | {load()}"
        )
        ours_png = next((tmp / "out0").rglob("*.png")).read_bytes()
        ref_png = (tmp / "min1.png").read_bytes()
        print(f"  same PNG bytes as the minimal script: {ours_png == ref_png}")

        out = tmp / "importtime"
        res = subprocess.run(
            [sys.executable, "-X", "importtime", "-m", "sparsetools.cli.main", "-q", "project",
             str(cloud), "--calib", str(calib), "--image-size", "1242x375", "-o", str(out)],
            capture_output=True, text=True, env=env(), check=True,
        )  # fmt: skip
    top: list[tuple[int, str]] = []
    loaded = set()
    for line in res.stderr.splitlines():
        parts = line.split("|")
        if not line.startswith("import time:") or len(parts) != 3 or not parts[1].strip().isdigit():
            continue
        name = parts[2].strip()
        loaded.add(name.split(".")[0])
        if len(parts[2]) - len(parts[2].lstrip()) == 1:  # not nested in another import
            top.append((int(parts[1]), name))
    top.sort(reverse=True)
    print("  heaviest top-level imports (cumulative ms): "
          + ", ".join(f"{n} {us / 1e3:.0f}" for us, n in top[:8]))  # fmt: skip
    heavy = [m for m in HEAVY if m in loaded]
    print(f"  heavy libraries imported: {', '.join(heavy) if heavy else 'none'} (checked: "
          f"{', '.join(HEAVY)})")  # fmt: skip


if __name__ == "__main__":
    main()
