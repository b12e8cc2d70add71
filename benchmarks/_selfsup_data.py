"""Synthetic street videos as sparsetools datasets, through the command line (shared by the
self-supervised acceptance runs: acceptance_selfsup.py, acceptance_sfe.py).

Every step is a `sparsetools` command, as a user would run it:

    sparsetools synth-scene -o VIDEOS --video --sequences S --frames F --image-size WxH --seed 100
    sparsetools beams VIDEOS/<seq>/velodyne --n 1,2,4,16 -o BEAMS/<seq>
    sparsetools project BEAMS/<seq>/n<N> --calib VIDEOS/<seq>/calib --image VIDEOS/<seq>/image_2 \
        -o SPARSE<N>/<seq>
    sparsetools lowlight-synth VIDEOS/<seq>/image_2 --depth ... --calib ... -o NIGHT/<seq> ...
    sparsetools dataset build -o DS --rgb STAGE/rgb --sparse SPARSE<N> --gt STAGE/gt \
        --calib STAGE/calib --splits train=...,val=...,test=...

Existing outputs are reused (each command resumes; datasets with a manifest are kept). The datasets
are built from flat staging folders (night images live apart from their videos), which carry
no poses, so :func:`attach_true_poses` fills the manifest's ``T_world_cam`` from the videos'
poses.txt (pose evaluation needs it; `dataset build --rgb VIDEOS` reads them itself).
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def sparsetools(*args, capture: bool = False) -> str:
    """Run one `sparsetools` command (quiet); exit with its error on failure."""
    cmd = [sys.executable, "-m", "sparsetools.cli.main", "-q", *map(str, args)]
    print("$ sparsetools " + " ".join(map(str, args)), flush=True)
    res = subprocess.run(
        cmd,
        check=False,
        text=True,
        stdout=subprocess.PIPE if capture else subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    if res.returncode != 0:
        sys.exit(f"command failed ({res.returncode}): {' '.join(cmd)}\n{res.stderr}")
    return res.stdout if capture else ""


@dataclass(frozen=True)
class VideoSettings:
    """What the videos and the datasets are made of.

    size : (width, height) pixels; sequences, frames : counts; split : `dataset build --split`;
    workers : processes of `synth-scene`; beams : beam counts to make; night_brightness : the
    lowlight-synth brightness of the night frames (None: no night frames).
    """

    size: tuple[int, int]
    sequences: int
    frames: int
    split: str
    workers: int = 2
    beams: tuple[int, ...] = (4, 16)
    night_brightness: float | None = None
    seed: int = 100
    #: keep every K-th azimuth step of the N-beam scans before projecting (1: all)
    azimuth_keep: int = 1


# -- where the commands put things (the only place that knows the folder layouts) ----------------
@dataclass(frozen=True)
class SequenceFiles:
    """Inputs and outputs of one video sequence."""

    name: str
    images: Path  # camera frames, <frame>.png
    depth: Path  # true dense depth, KITTI PNG
    calib: Path  # per-frame KITTI calib .txt
    velodyne: Path  # 64-beam scans .bin
    poses: Path  # KITTI odometry poses.txt (T_world_from_cam)
    beams: dict  # N -> folder of N-beam scans (written by `beams --n ... -o BEAMS/<seq>`)
    sparse: dict  # N -> folder of projected N-beam depth maps
    night: Path  # night frames (written by `lowlight-synth ... -o NIGHT/<seq>`)


def sequence_files(out: Path, name: str, beams: tuple[int, ...] = (4, 16)) -> SequenceFiles:
    video = out / "videos" / name
    return SequenceFiles(
        name=name,
        images=video / "image_2",
        depth=video / "depth_gt",
        calib=video / "calib",
        velodyne=video / "velodyne",
        poses=video / "poses.txt",
        beams={n: out / "beams" / name / f"n{n}" for n in beams},
        sparse={n: out / f"sparse{n}" / name for n in beams},
        night=out / "night" / name,
    )


def sequence_names(out: Path) -> list[str]:
    return sorted(p.name for p in (out / "videos").iterdir() if (p / "image_2").is_dir())


def link(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if not dst.exists():
        os.symlink(src.resolve(), dst)


# -- data -------------------------------------------------------------------------------------------
def prepare_datasets(
    out: Path, settings: VideoSettings, datasets: dict[str, tuple[str, int]], *, thin=None
) -> dict[str, Path]:
    """Videos, N-beam sparse depth, (night frames,) and one dataset per entry of ``datasets``.

    Parameters
    ----------
    out : Path
        Working folder.
    settings : VideoSettings
    datasets : dict
        Dataset key -> (images: 'rgb' or 'night', beam count of its sparse depth).
    thin : callable, optional
        ``thin(src, dst, settings.azimuth_keep)`` writes thinned copies of the N-beam scans
        (used when ``azimuth_keep > 1``).

    Returns
    -------
    dict of key -> dataset folder.
    """
    w, h = settings.size
    beams = settings.beams
    if not (out / "videos" / "video.json").is_file():
        sparsetools(
            "synth-scene", "-o", out / "videos", "--video", "--sequences", settings.sequences,
            "--frames", settings.frames, "--image-size", f"{w}x{h}", "--seed", settings.seed,
            "--workers", settings.workers, "--overwrite",
        )  # fmt: skip
    stage = out / "stage"
    night = settings.night_brightness is not None
    for name in sequence_names(out):
        f = sequence_files(out, name, beams)
        if not all(d.is_dir() for d in f.beams.values()):
            sparsetools(
                "beams", f.velodyne, "--n", ",".join(map(str, beams)), "-o",
                f.beams[beams[0]].parent,
            )  # fmt: skip
        for n in beams:
            scans = f.beams[n]
            if settings.azimuth_keep > 1:
                scans = out / f"beams_az{settings.azimuth_keep}" / name / f"n{n}"
                thin(f.beams[n], scans, settings.azimuth_keep)
            sparsetools(
                "project", scans, "--calib", f.calib, "--image", f.images, "-o", f.sparse[n]
            )
        if night:
            b = settings.night_brightness
            sparsetools(
                "lowlight-synth", f.images, "--depth", f.depth, "--calib", f.calib, "-o",
                f.night, "--seed", 0, "--brightness", f"{b},{b}", "--gamma", "2.0,2.0",
                "--no-flare",
            )  # fmt: skip
            link(f.night, stage / "night" / name)
        link(f.images, stage / "rgb" / name)
        link(f.depth, stage / "gt" / name)
        link(f.calib, stage / "calib" / name)
        for n in beams:
            link(f.sparse[n], stage / f"sparse{n}" / name)
    made = {}
    for key, (rgb, n) in datasets.items():
        ds = out / f"dataset_{key}"
        if not (ds / "manifest.parquet").is_file():
            sparsetools(
                "dataset", "build", "-o", ds, "--rgb", stage / rgb, "--sparse", stage / f"sparse{n}",
                "--gt", stage / "gt", "--calib", stage / "calib", "--source", f"lidar-{n}beam",
                "--splits", settings.split, "--seed", 0, "--sparse-format", "png",
            )  # fmt: skip
        attach_true_poses(ds, out)
        made[key] = ds
    return made


def attach_true_poses(ds: Path, out: Path) -> None:
    """Fill the manifest's T_world_cam from the videos' poses.txt where `dataset build` left it
    empty (it reads poses from nuScenes only so far); pose evaluation needs it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from sparsetools.io.poses import read_kitti_poses

    table = pq.read_table(ds / "manifest.parquet")
    if "T_world_cam" in table.column_names and table.column("T_world_cam").null_count == 0:
        return
    poses = {
        name: read_kitti_poses(sequence_files(out, name).poses) for name in sequence_names(out)
    }
    index = table.column("frame_index").to_pylist()
    values = [
        [float(v) for v in np.asarray(poses[s][i]).ravel()]
        for s, i in zip(table.column("sequence").to_pylist(), index, strict=True)
    ]
    column = pa.array(values, pa.list_(pa.float64()))
    names = table.column_names
    table = (
        table.set_column(names.index("T_world_cam"), "T_world_cam", column)
        if "T_world_cam" in names
        else table.append_column("T_world_cam", column)
    )
    pq.write_table(table, ds / "manifest.parquet")
