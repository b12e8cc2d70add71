"""Training of the learned densifier (:mod:`.densifier`) on synthetic streets with exact truth.

``sparsetools train-densifier`` runs :func:`train_densifier`:

1. **Frames.** The street frames of ``synth-scene`` folders (``velodyne/*.bin``,
   ``velodyne_ring/*.npy``, ``calib/*.txt``, ``depth_gt/*.png``: the dense truth), or, without
   a folder, ``sim_frames`` frames simulated in memory (:func:`sparsetools.synth.simulate_frame`,
   seed ``seed``, one frame every :data:`SIM_STRIDE_M` metres along the street). Each frame's
   scan is thinned to every beam count of ``beam_counts`` (64: the whole scan; 8, 16, 32: every
   ``64 / N``-th laser; 1-4: the lasers nearest the horizon, :func:`~sparsetools.ops.beams.select_beams`)
   and projected (:func:`~sparsetools.ops.projection.project_points`, nearest point wins).
2. **Samples.** Each step draws ``batch_size`` samples from a generator seeded by
   ``(seed, step)``: a frame, a beam count, a random ``tile_size`` window, a horizontal flip
   with probability 0.5 and, with probability ``corrupt``, a **corrupted rectangle** (a
   quarter to a half of the tile's height, a sixth to a third of its width) in which every
   measured depth is multiplied by ``exp(N(0, 0.5^2))`` while the target stays the truth: the
   network learns to distrust measurements that disagree with their neighbours (LiDAR
   outliers: rain, glass, blooming, points seen through a gap) and to say so in ``U``.
3. **Steps.** Adam, learning rate ``lr`` with a cosine decay to 0 over ``steps``, loss
   :func:`~.densifier.densifier_loss` on the truth up to ``max_depth``; deterministic
   algorithms and ``threads`` torch threads (:func:`~.runtime.torch_settings`): the same
   configuration gives the same weights, bit for bit, on the same machine and thread count.
4. **Files** in the run folder, each written atomically: ``densifier.pt`` (the checkpoint),
   ``metrics.csv`` (every ``log_every`` steps: step, lr, l1, nll, loss, seconds) and
   ``config.json`` (configuration, run id, summary). A folder that holds anything is refused
   unless ``overwrite``.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..errors import FormatError, OutputError, ParameterError
from ..validate import (
    check_choice,
    check_int_range,
    check_nonempty,
    check_positive,
    check_probability,
    check_range,
)
from .checkpoint import new_run_id
from .densifier import (
    CHECKPOINT_NAME,
    SparseDensifier,
    classical_base,
    densifier_loss,
    save_densifier,
)
from .runtime import (
    progress_bar,
    resolve_device,
    torch_settings,
    write_csv,
    write_json,
)

__all__ = [
    "CORRUPT_SIGMA",
    "METRICS_COLUMNS",
    "SIM_STRIDE_M",
    "DensifierRun",
    "DensifierTrainConfig",
    "StreetMaps",
    "corrupt_rectangle",
    "draw_batch",
    "fit_densifier",
    "load_scene_frames",
    "simulate_frames",
    "sparse_maps",
    "train_densifier",
]

#: Metres between simulated frames (the ego drives 1 m per frame index).
SIM_STRIDE_M = 7
#: Standard deviation of the log-normal factor of a corrupted measurement.
CORRUPT_SIGMA = 0.5
#: Beam counts a 64-laser scan can be thinned to (uniform: 8-32; horizon: 1-4).
BEAM_COUNTS = (1, 2, 3, 4, 8, 16, 32, 64)
METRICS_COLUMNS = ["step", "lr", "l1", "nll", "loss", "seconds"]
_STREAM_BATCH = 11


@dataclass(frozen=True)
class DensifierTrainConfig:
    """The settings of a densifier training run (module docstring; recorded in its files).

    Attributes
    ----------
    scenes : tuple of str
        ``synth-scene`` street folders; empty: simulate ``sim_frames`` frames.
    sim_frames : int
        Frames simulated when no folder is given (>= 1).
    image_size : (W, H)
        Size of the simulated frames, pixels (the size the densifier will be used at).
    beam_counts : tuple of int
        Beam counts the inputs are thinned to (each of :data:`BEAM_COUNTS`).
    steps, batch_size : int
        Optimizer steps and samples per step.
    tile_size : (W, H)
        Window of a frame per sample, pixels (clipped to the frame).
    lr : float
        Initial learning rate (cosine decay to 0).
    width : int
        The network's first-level width.
    reference_depth : float, metres
    max_depth : float, metres
        Truth beyond it is not trained on.
    nll_weight : float
        Weight ``w`` of the heteroscedastic term.
    corrupt : float
        Probability of a corrupted rectangle per sample, in [0, 1].
    seed : int
        Scene (when simulated), weights and samples.
    threads : int or None
        torch CPU threads (None: :func:`~.runtime.default_threads`).
    device : str
    log_every : int
        Steps per row of ``metrics.csv``.
    """

    scenes: tuple[str, ...] = ()
    sim_frames: int = 12
    image_size: tuple[int, int] = (1242, 375)
    beam_counts: tuple[int, ...] = (64, 16, 4)
    steps: int = 300
    batch_size: int = 4
    tile_size: tuple[int, int] = (256, 128)
    lr: float = 2e-3
    width: int = 8
    reference_depth: float = 10.0
    max_depth: float = 80.0
    nll_weight: float = 1.0
    corrupt: float = 0.0
    seed: int = 0
    threads: int | None = None
    device: str = "cpu"
    log_every: int = 25

    def __post_init__(self) -> None:
        object.__setattr__(self, "scenes", tuple(str(s) for s in self.scenes))
        check_int_range(self.sim_frames, "sim_frames", low=1)
        for name in ("image_size", "tile_size"):
            w, h = getattr(self, name)
            object.__setattr__(self, name, (check_int_range(w, name, low=16),
                                            check_int_range(h, name, low=16)))  # fmt: skip
        check_nonempty(self.beam_counts, "beam_counts")
        for n in self.beam_counts:
            check_choice(str(n), "beam_counts", [str(b) for b in BEAM_COUNTS])
        object.__setattr__(self, "beam_counts", tuple(int(n) for n in self.beam_counts))
        check_int_range(self.steps, "steps", low=1)
        check_int_range(self.batch_size, "batch_size", low=1)
        check_positive(self.lr, "lr")
        check_int_range(self.width, "width", low=1, high=256)
        check_positive(self.reference_depth, "reference_depth")
        check_positive(self.max_depth, "max_depth")
        check_range(self.nll_weight, "nll_weight", low=0.0)
        check_probability(self.corrupt, "corrupt", open_low=False)
        check_int_range(self.seed, "seed", low=0)
        if self.threads is not None:
            check_int_range(self.threads, "threads", low=1)
        check_int_range(self.log_every, "log_every", low=1)
        resolve_device(self.device)

    def to_dict(self) -> dict:
        """JSON-ready (lists for tuples)."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        return d


# -- frames --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StreetMaps:
    """One street frame as training sees it.

    Attributes
    ----------
    name : str
    gt : (H, W) float32, metres
        Exact depth, 0 = no truth (sky, beyond 250 m).
    sparse : dict of int to (H, W) float32, metres
        The scan thinned to each beam count and projected; 0 = no measurement.
    """

    name: str
    gt: np.ndarray
    sparse: dict = field(default_factory=dict)


def sparse_maps(points: np.ndarray, ring: np.ndarray, calib, beams: tuple[int, ...]) -> dict:
    """The scan thinned to each of ``beams`` and projected: ``{n: (H, W) float32 metres}``.

    Parameters
    ----------
    points : (N, 4) float32, metres
        A 64-laser scan (the synthetic HDL-64E's).
    ring : (N,) int
        Laser per point, 0 = highest.
    calib : Calibration
        Scan -> camera, with the image size.
    beams : tuple of int
    """
    from ..ops.beams import select_beams
    from ..ops.projection import project_points
    from ..synth import hdl64_elevations_deg

    out = {}
    for n in beams:
        if n == 64:
            kept = points
        else:
            kept = select_beams(points, ring, n=n, select="horizon" if n <= 4 else "uniform",
                                ring_elevation_deg=hdl64_elevations_deg()).points  # fmt: skip
        out[n] = project_points(kept, calib, backend="compiled")
    return out


def simulate_frames(
    seed: int, frames: int, *, width: int, height: int, beams: tuple[int, ...], progress=None
) -> list[StreetMaps]:
    """``frames`` street frames of the seed's street, :data:`SIM_STRIDE_M` metres apart,
    simulated in memory (about 0.5 s per 1242x375 frame)."""
    from ..synth import Rig, make_textures, simulate_frame, sun_direction

    rig = Rig.kitti(width, height)
    textures, sun = make_textures(seed), sun_direction(seed)
    out = []
    for i in range(frames):
        f = simulate_frame(seed, i * SIM_STRIDE_M, rig=rig, textures=textures, sun=sun)
        out.append(StreetMaps(f"seed{seed}/{i * SIM_STRIDE_M:06d}", f.depth,
                              sparse_maps(f.points, f.ring, rig.calibration, beams)))  # fmt: skip
        if progress is not None:
            progress.update(1)
    return out


def load_scene_frames(folder: str | Path, *, beams: tuple[int, ...]) -> list[StreetMaps]:
    """The street frames of a ``synth-scene`` folder (module docstring, step 1).

    Raises
    ------
    FormatError
        Not a street folder (no ``velodyne/*.bin``), or a frame without its ring, calib or
        truth file.
    """
    from ..io.calib import load_calibration
    from ..io.depth_files import read_depth_file
    from ..io.kitti import read_velodyne_bin
    from ..io.npy import load_npy, read_map_bytes

    folder = Path(folder)
    scans = sorted((folder / "velodyne").glob("*.bin"))
    if not scans:
        raise FormatError(
            f"{folder}: no velodyne/*.bin (give folders written by `sparsetools synth-scene`)"
        )
    out = []
    for scan in scans:
        stem = scan.stem
        paths = {
            "ring": folder / "velodyne_ring" / f"{stem}.npy",
            "calib": folder / "calib" / f"{stem}.txt",
            "truth": folder / "depth_gt" / f"{stem}.png",
        }
        for what, p in paths.items():
            if not p.is_file():
                raise FormatError(f"{p}: no such file (the {what} of {scan.name}; synth-scene "
                                  "writes one per frame)")  # fmt: skip
        gt = read_depth_file(paths["truth"])
        ring = load_npy(read_map_bytes(paths["ring"], what="ring"), source=str(paths["ring"]))
        points = read_velodyne_bin(scan)
        if ring.shape != (points.shape[0],) or ring.dtype.kind not in "iu":
            raise FormatError(f"{paths['ring']}: not one integer ring per point of {scan.name}")
        calib = load_calibration(paths["calib"], image_size=(gt.shape[1], gt.shape[0]))
        out.append(StreetMaps(f"{folder.name}/{stem}", gt,
                              sparse_maps(points, ring, calib, beams)))  # fmt: skip
    return out


# -- samples -------------------------------------------------------------------------------------


def corrupt_rectangle(
    sparse: np.ndarray, rng: np.random.Generator, *, sigma: float = CORRUPT_SIGMA
) -> tuple[np.ndarray, np.ndarray]:
    """A copy of ``sparse`` whose measurements in one random rectangle are made wrong.

    Parameters
    ----------
    sparse : (H, W) float32, metres
    rng : numpy.random.Generator
    sigma : float
        Each measured depth in the rectangle is multiplied by ``exp(N(0, sigma^2))``.

    Returns
    -------
    corrupted : (H, W) float32, metres
    region : (H, W) bool
        The rectangle.
    """
    h, w = sparse.shape
    rh = int(rng.integers(max(1, h // 4), max(2, h // 2) + 1))
    rw = int(rng.integers(max(1, w // 6), max(2, w // 3) + 1))
    top, left = int(rng.integers(0, h - min(rh, h) + 1)), int(rng.integers(0, w - min(rw, w) + 1))
    region = np.zeros((h, w), bool)
    region[top : top + rh, left : left + rw] = True
    factor = np.exp(rng.normal(0.0, sigma, size=(h, w))).astype(np.float32)
    hit = region & (sparse > 0)
    return np.where(hit, sparse * factor, sparse).astype(np.float32), region


def draw_batch(
    frames: list[StreetMaps],
    rng: np.random.Generator,
    *,
    batch_size: int,
    tile_size: tuple[int, int],
    beams: tuple[int, ...],
    corrupt: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``batch_size`` samples (module docstring, step 2).

    Returns
    -------
    sparse : (B, 1, h, w) float32, metres
    base : (B, 1, h, w) float32, metres
        :func:`~.densifier.classical_base` of each sample's (corrupted) sparse window.
    gt : (B, 1, h, w) float32, metres
        ``(h, w)``: ``tile_size`` (W, H) clipped to the smallest frame.
    """
    th = min([tile_size[1]] + [f.gt.shape[0] for f in frames])
    tw = min([tile_size[0]] + [f.gt.shape[1] for f in frames])
    sparse = np.zeros((batch_size, 1, th, tw), np.float32)
    base = np.zeros((batch_size, 1, th, tw), np.float32)
    gt = np.zeros((batch_size, 1, th, tw), np.float32)
    for b in range(batch_size):
        f = frames[int(rng.integers(len(frames)))]
        n = beams[int(rng.integers(len(beams)))]
        h, w = f.gt.shape
        top, left = int(rng.integers(0, h - th + 1)), int(rng.integers(0, w - tw + 1))
        s = f.sparse[n][top : top + th, left : left + tw]
        g = f.gt[top : top + th, left : left + tw]
        if rng.random() < 0.5:
            s, g = s[:, ::-1], g[:, ::-1]
        s = np.ascontiguousarray(s)
        if rng.random() < corrupt:
            s, _ = corrupt_rectangle(s, rng)
        sparse[b, 0], base[b, 0], gt[b, 0] = s, classical_base(s), g
    return sparse, base, gt


# -- training ------------------------------------------------------------------------------------


def _lr(config: DensifierTrainConfig, step: int) -> float:
    return config.lr * 0.5 * (1.0 + math.cos(math.pi * step / config.steps))


def fit_densifier(
    config: DensifierTrainConfig, frames: list[StreetMaps], *, progress: bool = False
) -> tuple[SparseDensifier, list[dict]]:
    """Train a densifier on ``frames`` (module docstring, steps 2-3), in memory.

    Returns
    -------
    model : SparseDensifier
        On CPU, in evaluation mode.
    history : list of dict
        One row per ``log_every`` steps (:data:`METRICS_COLUMNS`; the losses are the means
        over those steps).
    """
    check_nonempty(frames, "frames")
    device = resolve_device(config.device)
    history: list[dict] = []
    with torch_settings(config.threads, device):
        torch.manual_seed(config.seed)
        model = SparseDensifier(width=config.width, reference_depth=config.reference_depth)
        model.to(device).train()
        opt = torch.optim.Adam(model.parameters(), lr=config.lr)
        sums = {"l1": 0.0, "nll": 0.0, "loss": 0.0}
        start, count = time.perf_counter(), 0
        with progress_bar(config.steps, "train-densifier", progress, unit="step") as bar:
            for step in range(config.steps):
                rng = np.random.default_rng(np.random.SeedSequence([config.seed, _STREAM_BATCH,
                                                                    step]))  # fmt: skip
                sparse, base, gt = draw_batch(frames, rng, batch_size=config.batch_size,
                                        tile_size=config.tile_size, beams=config.beam_counts,
                                        corrupt=config.corrupt)  # fmt: skip
                lr = _lr(config, step)
                for group in opt.param_groups:
                    group["lr"] = lr
                depth, log_var = model(
                    torch.from_numpy(sparse).to(device), torch.from_numpy(base).to(device)
                )
                terms = densifier_loss(depth, log_var, torch.from_numpy(gt).to(device),
                                       nll_weight=config.nll_weight,
                                       max_depth=config.max_depth)  # fmt: skip
                opt.zero_grad(set_to_none=True)
                terms["loss"].backward()
                opt.step()
                for k in sums:
                    sums[k] += float(terms[k].detach())
                count += 1
                bar.update(1)
                if count == config.log_every or step == config.steps - 1:
                    row = {"step": step + 1, "lr": lr, "seconds": time.perf_counter() - start}
                    row.update({k: v / count for k, v in sums.items()})
                    history.append(row)
                    sums, count = dict.fromkeys(sums, 0.0), 0
                    bar.set_postfix(loss=f"{row['loss']:.3f}")
    return model.cpu().eval(), history


@dataclass(frozen=True)
class DensifierRun:
    """What :func:`train_densifier` did: its folder, run id, frames, parameters, the last
    row of ``metrics.csv`` and the time taken (seconds)."""

    out_dir: str
    checkpoint: str
    run_id: str
    frames: int
    parameters: int
    steps: int
    l1: float
    nll: float
    seconds: float

    def to_dict(self) -> dict:
        return asdict(self)


def _check_out_dir(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise OutputError(f"{out} is not empty: use --overwrite to replace the run in it, or "
                          "choose another folder")  # fmt: skip


def train_densifier(
    config: DensifierTrainConfig,
    out_dir: str | Path,
    *,
    overwrite: bool = False,
    progress: bool = False,
) -> DensifierRun:
    """Load or simulate the frames, train, and write the run folder (module docstring).

    Raises
    ------
    OutputError
        ``out_dir`` is a file, or holds anything and ``overwrite`` is off.
    FormatError
        A scene folder that is not a ``synth-scene`` street folder.
    ParameterError
        A scene folder inside ``out_dir`` or the reverse.
    """
    out = Path(out_dir)
    _check_out_dir(out, overwrite)
    for s in config.scenes:
        a, b = Path(s).resolve(), out.resolve()
        if a == b or b in a.parents or a in b.parents:
            raise ParameterError(f"the run folder {out} and the scene {s} overlap: keep them apart")
    start = time.perf_counter()
    if config.scenes:
        frames = [f for s in config.scenes for f in load_scene_frames(s, beams=config.beam_counts)]
    else:
        with progress_bar(config.sim_frames, "simulate", progress, unit="frame") as bar:
            w, h = config.image_size
            frames = simulate_frames(config.seed, config.sim_frames, width=w, height=h,
                                     beams=config.beam_counts, progress=bar)  # fmt: skip
    model, history = fit_densifier(config, frames, progress=progress)
    run_id = new_run_id()
    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / CHECKPOINT_NAME
    save_densifier(ckpt, model=model, config=config.to_dict(), history=history, run_id=run_id)
    write_csv(out / "metrics.csv", history, METRICS_COLUMNS)
    last = history[-1]
    run = DensifierRun(
        out_dir=str(out),
        checkpoint=str(ckpt),
        run_id=run_id,
        frames=len(frames),
        parameters=sum(p.numel() for p in model.parameters()),
        steps=config.steps,
        l1=round(float(last["l1"]), 5),
        nll=round(float(last["nll"]), 5),
        seconds=round(time.perf_counter() - start, 3),
    )
    write_json(out / "config.json", {"run_id": run_id, "config": config.to_dict(),
                                     "summary": run.to_dict()})  # fmt: skip
    return run


#: The files a run writes (what its folder's record lists).
RUN_FILES = (CHECKPOINT_NAME, "metrics.csv", "config.json")


def recorded_run(out: str | Path) -> DensifierRun | None:
    """The summary a finished run left in ``config.json`` (None when it cannot be read: the
    run is made again)."""
    import json

    try:
        summary = json.loads((Path(out) / "config.json").read_text("utf-8"))["summary"]
        return DensifierRun(**{f: summary[f] for f in DensifierRun.__dataclass_fields__})
    except (OSError, ValueError, KeyError, TypeError):
        return None
