"""``lowlight-synth`` throughput: the command line against a minimal loop, 1 vs 2 workers, Dask.

Run: ``.venv/bin/python benchmarks/bench_scale.py [N_IMAGES] [--no-dask]`` (``make bench`` runs
it with the others; default 24 images of 1242x375, copies of the synthetic street images).

1. ``sparsetools lowlight-synth IMAGES -o OUT --seed 0`` with ``--workers 1`` and ``2``,
   process start to exit, against a minimal in-process loop doing the same work
   (``read_image``, ``lowlight`` with the frame's seed, ``write_image``; the flare bank and
   SciPy already loaded, as they are after the first frame). Goals (issue 18): the command at
   >= 0.75x the loop's speed, 2 workers >= 1.7x one on an otherwise idle machine. Alternating
   runs, the machine's load on every line.
2. The same run on Dask (a ``LocalCluster`` of 1 and 2 single-threaded workers, started for the
   run): absolute times and the speed-up against the local serial run.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load

ROOT = Path(__file__).resolve().parent.parent
SYNTH = ROOT / "sample_data" / "synthetic"
ARGS = [a for a in sys.argv[1:] if not a.startswith("--")]
N_IMAGES = int(ARGS[0]) if ARGS and ARGS[0].isdigit() else 24
DASK = "--no-dask" not in sys.argv


def _images(root: Path) -> Path:
    folder = root / "images"
    folder.mkdir()
    for i in range(N_IMAGES):
        shutil.copy(SYNTH / "image_2" / f"{i % 3:06d}.png", folder / f"{i:06d}.png")
    return folder


def _env() -> dict:
    env = dict(os.environ)
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # a user's shell keeps bytecode caches
    return env


def main() -> None:
    from sparsetools.io.image import read_image, write_image
    from sparsetools.ops.lowlight import LowLightParams, lowlight
    from sparsetools.random import frame_rng

    exe = ROOT / ".venv" / "bin" / "sparsetools"
    cli = [str(exe)] if exe.exists() else [sys.executable, "-m", "sparsetools.cli.main"]
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        images = _images(root)
        files = sorted(images.glob("*.png"))
        runs = iter(range(10**6))
        params = LowLightParams()

        def command(*extra: str):
            def run():
                out = root / f"out{next(runs)}"
                subprocess.run([*cli, "-q", "lowlight-synth", str(images), "-o", str(out),
                                "--seed", "0", *extra],
                               check=True, env=_env(), stdout=subprocess.DEVNULL)  # fmt: skip
                return out

            return run

        def loop():
            out = root / f"loop{next(runs)}"
            out.mkdir()
            for f in files:
                rng = frame_rng(0, f"{f.stem}:0")
                night, _ = lowlight(read_image(f), rng=rng, params=params)
                write_image(out / f.name, night)
            return out

        a, b, c = command("--workers", "1")(), command("--workers", "2")(), loop()
        same = all((a / f.name).read_bytes() == (b / f.name).read_bytes() for f in files)
        same_loop = all((a / f.name).read_bytes() == (c / f.name).read_bytes() for f in files)
        print(f"lowlight-synth on {N_IMAGES} images of 1242x375 | {load()}")
        t = interleaved(
            {"loop": loop, "w1": command("--workers", "1"), "w2": command("--workers", "2")},
            repeat=3,
        )
        ratio, scaling = t["loop"] / t["w1"], t["w1"] / t["w2"]
        print(
            f"  minimal in-process loop {t['loop']:6.2f} s | --workers 1 {t['w1']:6.2f} s (process "
            f"start to exit) | ratio {ratio:4.2f}x (goal >= 0.75x: "
            f"{'met' if ratio >= 0.75 else 'NOT met'}) | {load()}"
        )
        print(
            f"  --workers 2 {t['w2']:6.2f} s | 2 vs 1 worker {scaling:4.2f}x (goal >= 1.7x on an "
            f"idle machine: {'met' if scaling >= 1.7 else 'NOT met'}) | {load()}"
        )
        print(f"  same images with 1 and 2 workers: {same}; as the loop's: {same_loop}")
        if not DASK:
            return
        for workers in ("1", "2"):
            t0 = time.perf_counter()
            command("--executor", "dask", "--workers", workers)()
            seconds = time.perf_counter() - t0
            print(
                f"  dask, {workers} worker(s) {seconds:7.2f} s  {N_IMAGES / seconds:6.2f} images/s "
                f"speed-up vs local serial {t['w1'] / seconds:4.2f}x | {load()}"
            )


if __name__ == "__main__":
    from sparsetools.pipeline.executors import limit_blas_threads

    with limit_blas_threads(1):
        main()
