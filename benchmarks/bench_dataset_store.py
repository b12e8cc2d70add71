"""Disk and loading speed of ``--store copy`` vs ``--store reference`` (issue 26).

On a KITTI raw tree made from the real sequence (``/work/shared/data/real/
kitti-raw-sequence-2011_09_26``, its 11 frames copied into ``<tmp>/raw/2011_09_26/...``, as
tests/test_real_trees.py builds one), four variants are built with ``dataset kitti-raw``
(``--beams 1, 4, 16, 64``) in each mode. Disk is counted as ``du`` counts it: allocated blocks
(``st_blocks * 512``) of every regular file under the folders, each inode once (hard links
and files named twice count once; a reflink's shared blocks cannot be told apart by ``stat``,
so the file system type is printed: ext4 and overlayfs have no reflinks). Then
``DataLoader`` samples/s through the torch ``Dataset`` recipe of docs/dataset.md ("Loading"),
on the 4-beam copy dataset and the 4-beam reference dataset, ``num_workers`` 0 and 2,
medians of alternating runs (page cache warm: the images are read from memory in both).

Run: ``PYTHONPATH=src .venv/bin/python benchmarks/bench_dataset_store.py [--repeat 5]``
"""

from __future__ import annotations

import argparse
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load

SEQ = Path("/work/shared/data/real/kitti-raw-sequence-2011_09_26")
DATE = "2011_09_26"
DRIVE = f"{DATE}_drive_0001_sync"
BEAMS = (1, 4, 16, 64)


def make_raw(root: Path) -> Path:
    """root/2011_09_26/{calib files, drive/{image_02, velodyne_points}/data/*} (copies)."""
    date = root / DATE
    date.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(SEQ / name, date / name)
    for sub in ("image_02", "velodyne_points"):
        shutil.copytree(SEQ / sub / "data", date / DRIVE / sub / "data")
    return root


def disk_bytes(*folders: Path, seen: set | None = None) -> int:
    """Allocated bytes of the regular files under ``folders``, each inode once (``du``)."""
    seen = set() if seen is None else seen
    total = 0
    for folder in folders:
        for d, _, names in os.walk(folder):
            for n in names:
                st = os.lstat(os.path.join(d, n))
                if stat.S_ISREG(st.st_mode) and (st.st_dev, st.st_ino) not in seen:
                    seen.add((st.st_dev, st.st_ino))
                    total += st.st_blocks * 512
    return total


def du(*folders: Path) -> int | None:
    """``du -s -B1`` over the folders together (hard links once), as a cross-check."""
    try:
        out = subprocess.run(["du", "-s", "-c", "-B1", *map(str, folders)], check=True,
                             capture_output=True, text=True).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None
    return int(out.strip().splitlines()[-1].split()[0])


def fs_type(path: Path) -> str:
    try:
        return subprocess.run(["stat", "-f", "-c", "%T", str(path)], check=True,
                              capture_output=True, text=True).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def mib(n: int) -> str:
    return f"{n / 2**20:8.2f} MiB"


def build_variants(raw: Path, base: Path) -> dict:
    from sparsetools.pipeline.batch import Batch
    from sparsetools.pipeline.dataset.roots import build_kitti_raw_dataset

    out = {}
    for store in ("copy", "reference"):
        for n in BEAMS:
            ds = base / store / f"beams{n}"
            t0 = time.perf_counter()
            build_kitti_raw_dataset(raw, ds, beams=None if n == 64 else n, store=store,
                                    batch=Batch(progress=False))  # fmt: skip
            out[(store, n)] = (ds, time.perf_counter() - t0)
    return out


def report_disk(raw: Path, built: dict) -> None:
    images = raw / DATE / DRIVE / "image_02"
    print(f"file system of the datasets: {fs_type(raw)}; raw images "
          f"{mib(disk_bytes(images))} ({len(list(images.rglob('*.png')))} PNGs)")  # fmt: skip
    print(f"{'variant':<22} {'build s':>8} {'dataset':>13} {'.sources':>13} {'total':>13}")
    totals = {}
    for (store, n), (ds, secs) in built.items():
        sources = disk_bytes(ds / ".sources")
        total = disk_bytes(ds)
        totals.setdefault(store, []).append(ds)
        print(f"{store + f' --beams {n}':<22} {secs:8.2f} {mib(total - sources)} "
              f"{mib(sources)} {mib(total)}")  # fmt: skip
    for store, folders in totals.items():
        seen: set = set()
        ours = disk_bytes(*folders, seen=seen)
        with_raw = ours + disk_bytes(images, seen=seen)
        print(f"4 variants, --store {store:<9}: {mib(ours)} in the datasets "
              f"(du -s: {mib(du(*folders) or 0)}); with the raw images they use: "
              f"{mib(with_raw)}")  # fmt: skip


def report_loading(built: dict, repeat: int) -> None:
    import torch

    from sparsetools.io.dataset_reader import DatasetReader

    class DepthDataset(torch.utils.data.Dataset):  # docs/dataset.md, "Loading"
        def __init__(self, root, split):
            self.reader = DatasetReader(root, split=split)

        def __len__(self):
            return len(self.reader)

        def __getitem__(self, i):
            s = self.reader[i]
            return {
                "rgb": torch.from_numpy(s["rgb"]).permute(2, 0, 1).float() / 255,
                "sparse": torch.from_numpy(s["sparse"])[None],
                "gt": torch.from_numpy(s["gt"])[None],
                "K": torch.from_numpy(s["intrinsics"]),
            }

    epochs = 4  # passes over the samples per timed run (ConcatDataset)

    def loader(ds_dir: Path, workers: int):
        split = DatasetReader(ds_dir).splits[0]
        data = torch.utils.data.ConcatDataset([DepthDataset(ds_dir, split)] * epochs)
        return torch.utils.data.DataLoader(data, batch_size=2, num_workers=workers)

    def one_pass(ds_dir: Path, workers: int):
        def fn():
            for _ in loader(ds_dir, workers):
                pass

        return fn

    copy_dir, ref_dir = built[("copy", 4)][0], built[("reference", 4)][0]
    n = epochs * len(DatasetReader(copy_dir))
    for workers in (0, 2):
        t = interleaved({"copy": one_pass(copy_dir, workers),
                         "reference": one_pass(ref_dir, workers)}, repeat=repeat)  # fmt: skip
        print(f"DataLoader num_workers={workers}, batch 2, {n} samples per run: "
              f"copy {n / t['copy']:6.1f} samples/s, reference {n / t['reference']:6.1f} "
              f"samples/s (ratio reference/copy {t['copy'] / t['reference']:.2f}) [{load()}]")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per loader setting")
    args = ap.parse_args()
    print(f"[{load()}]")
    with tempfile.TemporaryDirectory(prefix="bench_store_") as tmp:
        base = Path(tmp)
        raw = make_raw(base / "raw")
        built = build_variants(raw, base)
        report_disk(raw, built)
        report_loading(built, args.repeat)
    print(f"[{load()}]")


if __name__ == "__main__":
    main()
