"""Throughput of a batch command with 1 and 2 workers, local processes vs Dask.

The reference is the serial run (``--workers 1``, local): the ratio is the speed-up.
lowlight-synth on copies of the synthetic street images (CPU-bound, ~0.3 s per image).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

from click.testing import CliRunner

from sparsetools.cli.main import cli

SYNTH = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"
N_IMAGES = int(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1].isdigit() else 24


def _images(root: Path) -> Path:
    folder = root / "images"
    folder.mkdir()
    for i in range(N_IMAGES):
        shutil.copy(SYNTH / "image_2" / f"{i % 3:06d}.png", folder / f"{i:06d}.png")
    return folder


def _run(images: Path, out: Path, extra: list[str]) -> float:
    t0 = time.perf_counter()
    r = CliRunner().invoke(
        cli, ["-q", "lowlight-synth", str(images), "-o", str(out), "--seed", "0", *extra]
    )
    if r.exit_code != 0:
        raise SystemExit(r.output)
    return time.perf_counter() - t0


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        images = _images(root)
        _run(images, root / "warm", ["--workers", "1"])  # numba caches, flare bank code paths
        configs = [
            ("local, 1 worker", ["--workers", "1"]),
            ("local, 2 workers", ["--workers", "2"]),
            ("dask, 1 worker", ["--executor", "dask", "--workers", "1"]),
            ("dask, 2 workers", ["--executor", "dask", "--workers", "2"]),
        ]
        base = None
        print(f"lowlight-synth on {N_IMAGES} images of 1242x375 (wall time includes start-up)")
        for i, (name, extra) in enumerate(configs):
            seconds = _run(images, root / f"out{i}", extra)
            base = base or seconds
            print(
                f"{name:<18} {seconds:7.2f} s  {N_IMAGES / seconds:6.2f} images/s  "
                f"speed-up vs serial {base / seconds:4.2f}x"
            )


if __name__ == "__main__":
    main()
