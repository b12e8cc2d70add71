"""Dataset build throughput on 200 synthetic 320x96 frames, and where the time goes.

Ours (``build_dataset``: decode-check, hash, atomic writes, staging, Parquet parts, manifest,
the resume record) with ``--workers 1`` and ``2`` against a straightforward serial script that
does the same file work without resume (copy, decode rgb and gt as the build's checks do,
encode the sparse PNG, hash, one manifest at the end), and against the same script without
any decoding (a copy loop), in alternating runs with the machine's load on every line. Goals (issue
18): the serial build not slower than the plain loop (ratio >= 1), 2 workers >= 1.7x one on an
otherwise idle machine. Then the per-stage seconds that ``build_dataset`` reports for the
serial run, per-frame micro timings and the Parquet work alone.

Run: ``.venv/bin/python benchmarks/bench_dataset.py [--frames 200]``
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load, median_seconds

W, H = 320, 96


def make_inputs(root: Path, frames: int) -> Path:
    """Random RGB PNGs, sparse depth .npy (5 % of pixels, float32) and dense GT PNGs."""
    from sparsetools.io.image import write_depth_png, write_image

    rng = np.random.default_rng(0)
    for i in range(frames):
        seq = f"seq{i // 20:02d}"
        key = f"{seq}/{i:06d}"
        write_image(root / "rgb" / f"{key}.png", rng.integers(0, 256, (H, W, 3), dtype=np.uint8))
        d = np.where(rng.random((H, W)) < 0.05, rng.uniform(1, 80, (H, W)), 0).astype(np.float32)
        (root / "sparse" / seq).mkdir(parents=True, exist_ok=True)
        np.save(root / "sparse" / f"{key}.npy", d)
        write_depth_png(root / "gt" / f"{key}.png", rng.uniform(1, 80, (H, W)))
    return root


def reference_build(inputs: Path, out: Path, *, checks: bool = False) -> None:
    """Plain serial loop: copy rgb/gt, encode sparse PNG, points lists, hash, write tables once.

    With ``checks``, it also decodes what ``build_dataset`` decodes to check a frame and to
    fill its manifest row: the rgb image (readable, its size) and the gt map (its valid-pixel
    count). Without, it does no decoding at all (the lower bound of a copy loop).
    """
    import cv2
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows, parts = [], {"id": [], "u": [], "v": [], "depth": [], "height": [], "width": []}
    for rgb in sorted((inputs / "rgb").rglob("*.png")):
        key = rgb.relative_to(inputs / "rgb").with_suffix("").as_posix()
        row = {"id": key}
        for kind, src in (("rgb", rgb), ("gt", inputs / "gt" / f"{key}.png")):
            dst = out / kind / f"{key}.png"
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, dst)
            if checks:
                img = cv2.imdecode(np.fromfile(src, np.uint8), cv2.IMREAD_UNCHANGED)
                row[f"{kind}_size"] = img.shape[:2]
                if kind == "gt":
                    row["n_gt"] = int(np.count_nonzero(img))
            row[f"{kind}_sha256"] = hashlib.sha256(dst.read_bytes()).hexdigest()
        depth = np.load(inputs / "sparse" / f"{key}.npy")
        png = np.clip(np.rint(depth.astype(np.float64) * 256), 0, 65535).astype(np.uint16)
        dst = out / "sparse" / f"{key}.png"
        dst.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(dst), png)
        row["sparse_sha256"] = hashlib.sha256(dst.read_bytes()).hexdigest()
        v, u = np.nonzero(depth)
        for k, val in (
            ("id", key),
            ("u", u.astype(np.uint16)),
            ("v", v.astype(np.uint16)),
            ("depth", depth[v, u]),
            ("height", H),
            ("width", W),
        ):
            parts[k].append(val)
        rows.append(row)
    pq.write_table(pa.Table.from_pylist(rows), out / "manifest.parquet", compression="zstd")
    pq.write_table(
        pa.table(
            {
                "id": parts["id"],
                "u": pa.array(parts["u"], type=pa.list_(pa.uint16())),
                "v": pa.array(parts["v"], type=pa.list_(pa.uint16())),
                "depth": pa.array(parts["depth"], type=pa.list_(pa.float32())),
                "height": parts["height"],
                "width": parts["width"],
            }
        ),
        out / "sparse" / "part-00000.parquet",
        compression="zstd",
    )


def main(argv=None) -> dict:
    from sparsetools.pipeline import Batch
    from sparsetools.pipeline.dataset import build_dataset

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)

    tmp = Path(tempfile.mkdtemp(prefix="bench-dataset-"))
    counter = itertools.count()
    try:
        inputs = make_inputs(tmp / "in", args.frames)
        last = {}

        def ours(workers: int):
            def fn():
                out = tmp / f"ds{next(counter)}"
                last[workers] = build_dataset(
                    out,
                    rgb=inputs / "rgb",
                    sparse=inputs / "sparse",
                    gt=inputs / "gt",
                    batch=Batch(workers=workers, progress=False),
                )
                shutil.rmtree(out)

            return fn

        def reference(checks: bool):
            def fn():
                out = tmp / f"ref{next(counter)}"
                reference_build(inputs, out, checks=checks)
                shutil.rmtree(out)

            return fn

        n = args.frames
        print(
            f"dataset build, {n} frames of {W}x{H} (rgb PNG + sparse .npy -> PNG and Parquet "
            f"+ gt PNG) | {load()}"
        )
        t = interleaved(
            {"copy": reference(False), "ref": reference(True), "w1": ours(1), "w2": ours(2)},
            repeat=args.repeat,
        )
        serial, scaling = t["ref"] / t["w1"], t["w1"] / t["w2"]
        print(
            f"  serial loop with the same checks {t['ref'] * 1e3:8.1f} ms ({n / t['ref']:.0f} "
            f"frames/s) | build --workers 1 {t['w1'] * 1e3:8.1f} ms ({n / t['w1']:.0f} "
            f"frames/s) | ratio {serial:4.2f}x (goal >= 1: {'met' if serial >= 1 else 'NOT met'})"
            f" | {load()}"
        )
        print(
            f"  copy loop without decoding {t['copy'] * 1e3:8.1f} ms ({n / t['copy']:.0f} "
            f"frames/s) | ratio {t['copy'] / t['w1']:4.2f}x (the cost of checks + resume) | "
            f"{load()}"
        )
        print(
            f"  build --workers 2 {t['w2'] * 1e3:8.1f} ms ({n / t['w2']:.0f} frames/s) | 2 vs 1 "
            f"worker {scaling:4.2f}x (goal >= 1.7x on an idle machine: "
            f"{'met' if scaling >= 1.7 else 'NOT met'}) | {load()}"
        )
        stages = dict(last[1].totals["stage_seconds"])
        total = last[1].seconds + stages.get("t_plan", 0.0) + stages.get("t_finalize", 0.0)
        stages["other"] = max(0.0, total - sum(stages.values()))  # runner, stale-file scan
        print(f"where the time goes (last --workers 1 build, {total:.3f} s wall):")
        for k, v in sorted(stages.items(), key=lambda kv: -kv[1]):
            print(f"  {k:<11} {v:7.3f} s  {100 * v / total:5.1f} %")

        # Per-frame micro timings of the costs the issue asks about.
        from sparsetools.io.image import encode_depth_png

        depth = np.load(next((inputs / "sparse").rglob("*.npy")))
        rgb_bytes = next((inputs / "rgb").rglob("*.png")).read_bytes()
        t_png = median_seconds(lambda: encode_depth_png(depth), repeat=50)
        t_hash = median_seconds(lambda: hashlib.sha256(rgb_bytes).hexdigest(), repeat=50)
        print(
            f"per frame: sparse PNG encode {t_png * 1e3:.3f} ms, sha256 of a "
            f"{len(rgb_bytes) / 1024:.0f} KB rgb PNG {t_hash * 1e3:.3f} ms | {load()}"
        )

        # The Parquet work of the finalize step, alone: the part of all frames, the manifest.
        from sparsetools.io.dataset import (
            MANIFEST_SCHEMA,
            depth_to_points,
            read_manifest,
        )
        from sparsetools.io.dataset_parts import write_sparse_part
        from sparsetools.io.manifest_writer import write_manifest
        from sparsetools.io.points_table import sparse_part_table

        ids, points = [], []
        for p in sorted((inputs / "sparse").rglob("*.npy")):
            ids.append(p.relative_to(inputs / "sparse").with_suffix("").as_posix())
            points.append(depth_to_points(np.load(p)))
        built = tmp / "parquet"
        build_dataset(built, rgb=inputs / "rgb", sparse=inputs / "sparse",
                      batch=Batch(progress=False))  # fmt: skip
        manifest = read_manifest(built / "manifest.parquet")[0].select(MANIFEST_SCHEMA.names)

        def part():
            write_sparse_part(tmp / "part.parquet", sparse_part_table(ids, points, [(H, W)] * n))

        t_part = median_seconds(part, repeat=5)
        t_manifest = median_seconds(lambda: write_manifest(tmp / "m.parquet", manifest), repeat=5)
        print(
            f"Parquet: sparse part of {n} frames {t_part * 1e3:.1f} ms, "
            f"manifest of {n} rows {t_manifest * 1e3:.1f} ms | {load()}"
        )
        return {
            "seconds": t,
            "stages": stages,
            "png_encode_ms": t_png * 1e3,
            "sha256_ms": t_hash * 1e3,
            "part_ms": t_part * 1e3,
            "manifest_ms": t_manifest * 1e3,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    from sparsetools.pipeline.executors import limit_blas_threads

    with limit_blas_threads(1):
        main()
