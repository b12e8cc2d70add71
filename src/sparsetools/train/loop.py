"""Training and evaluation loops: checkpoints, exact resume, curves and prediction pictures.

A run folder holds::

    RUN_DIR/
      config.json           the training configuration
      metrics.csv           one row per epoch: train loss, validation loss and metrics
      last.pt, best.pt      checkpoints (best = lowest validation RMSE)
      curves.png            loss and validation RMSE per epoch
      predictions/epoch_NNN.png   rgb | sparse | prediction | gt for a few validation samples

Reproducibility: the model is initialised from ``torch.manual_seed(seed)``; the order of the
training samples of epoch ``e`` is a permutation drawn from ``(seed, e)`` and each sample's
augmentation from ``(seed, e, index)`` (:mod:`sparsetools.train.data`), so neither depends on
the number of DataLoader workers. ``torch.use_deterministic_algorithms`` is on while training.
On CPU two runs with the same seed (and thread count) give identical metrics, and a run resumed
from ``last.pt`` -- saved at the end of every epoch, or where ``max_steps`` stopped it, with the
model, optimizer, RNG states and the position inside the epoch -- continues exactly as if it
had never stopped.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from ..errors import FormatError, OutputError, ParameterError, SparsetoolsError
from ..io.atomic import atomic_path
from ..ops.metrics import METRIC_NAMES, aggregate_metrics, depth_metrics
from .data import DepthDataset, collate_samples
from .losses import LOSSES, depth_loss
from .model import INPUT_CHANNELS, STRIDE, DepthCompletionUNet, build_model, model_inputs

__all__ = [
    "CHECKPOINT_FORMAT",
    "TrainConfig",
    "draw_curves",
    "epoch_lr",
    "evaluate_checkpoint",
    "evaluate_folders",
    "load_checkpoint",
    "prediction_picture",
    "train",
    "write_eval_results",
]

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "sparsetools-depth-checkpoint"
CHECKPOINT_VERSION = 1
#: Files whose presence marks a folder as a run folder.
RUN_FILES = ("last.pt", "best.pt", "metrics.csv")


@dataclass
class TrainConfig:
    """Everything that defines a training run (saved in ``config.json`` and checkpoints).

    ``crop`` is (height, width); ``max_steps`` caps the total number of optimizer steps.
    ``workers``, ``device`` and ``threads`` do not change the results on CPU.
    """

    dataset: str
    out_dir: str
    input_mode: str = "rgbd"
    loss: str = "l1"
    epochs: int = 20
    batch_size: int = 8
    lr: float = 1e-3
    optimizer: str = "adam"
    lr_schedule: str = "constant"
    lr_step: int = 5
    lr_gamma: float = 0.5
    crop: tuple[int, int] | None = None
    seed: int = 0
    width: int = 32
    final_layer: bool = False
    workers: int = 0
    max_steps: int | None = None
    device: str = "cpu"
    train_split: str = "train"
    val_split: str = "val"
    max_depth: float = 80.0
    pictures: int = 3
    threads: int | None = None
    scale_range: tuple[float, float] = (1.0, 1.0)
    jitter: float = 0.2

    #: Fields that may change when a run is resumed (they do not alter the maths).
    RESUMABLE = ("epochs", "max_steps", "workers", "device", "threads", "pictures")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["crop"] = list(self.crop) if self.crop is not None else None
        d["scale_range"] = list(self.scale_range)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        if kw.get("crop") is not None:
            kw["crop"] = tuple(int(v) for v in kw["crop"])
        if "scale_range" in kw:
            kw["scale_range"] = tuple(float(v) for v in kw["scale_range"])
        return cls(**kw)

    def validate(self) -> None:
        if self.input_mode not in INPUT_CHANNELS:
            raise ParameterError(
                f"unknown input mode {self.input_mode!r}; choose one of {sorted(INPUT_CHANNELS)}"
            )
        if self.loss not in LOSSES:
            raise ParameterError(f"unknown loss {self.loss!r}; choose one of {sorted(LOSSES)}")
        if self.lr_schedule not in ("constant", "step", "cosine"):
            raise ParameterError(
                f"unknown learning-rate schedule {self.lr_schedule!r}; "
                "choose constant, step or cosine"
            )
        if self.lr_step < 1 or not 0 < self.lr_gamma <= 1:
            raise ParameterError(
                f"need lr_step >= 1 and 0 < lr_gamma <= 1, got {self.lr_step}, {self.lr_gamma}"
            )
        if self.optimizer not in ("adam", "sgd"):
            raise ParameterError(f"unknown optimizer {self.optimizer!r}; choose adam or sgd")
        for name in ("epochs", "batch_size", "width"):
            if int(getattr(self, name)) < 1:
                raise ParameterError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ParameterError(f"learning rate must be positive, got {self.lr}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ParameterError(f"max_steps must be >= 1, got {self.max_steps}")
        if self.workers < 0:
            raise ParameterError(f"workers must be >= 0, got {self.workers}")
        if not (self.max_depth > 0 and math.isfinite(self.max_depth)):
            raise ParameterError(f"max_depth must be positive, got {self.max_depth}")
        if self.pictures < 0:
            raise ParameterError(f"pictures must be >= 0, got {self.pictures}")
        if self.crop is not None and (len(self.crop) != 2 or min(self.crop) < 1):
            raise ParameterError(f"crop must be two positive sizes (H, W), got {self.crop}")
        _device(self.device)


# -- helpers ---------------------------------------------------------------------------------------
def _device(name: str) -> torch.device:
    if name == "cpu":
        return torch.device("cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ParameterError(f"device {name!r} requested but CUDA is not available here")
        return torch.device(name)
    raise ParameterError(f"unknown device {name!r}; use cpu or cuda")


def _available_cores() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def _torch_settings(threads: int | None, device: torch.device):
    """Deterministic algorithms and a thread count for the duration of a run, then restored."""
    prev_det = torch.are_deterministic_algorithms_enabled()
    prev_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    prev_threads = torch.get_num_threads()
    if device.type == "cuda":  # cuBLAS needs this for deterministic matrix products
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=device.type != "cpu")
    torch.set_num_threads(int(threads) if threads else _available_cores())
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(prev_det, warn_only=prev_warn)
        torch.set_num_threads(prev_threads)


def _worker_init(worker_id: int) -> None:
    # Augmentation uses explicit per-sample generators; this only keeps any other library's
    # global RNG reproducible in worker processes and avoids oversubscribing the cores.
    import random

    seed = torch.initial_seed() % 2**32
    np.random.seed(seed)  # noqa: NPY002 - global state of third-party code, not ours
    random.seed(seed)
    torch.set_num_threads(1)


def _epoch_order(seed: int, epoch: int, n: int) -> list[int]:
    return np.random.default_rng([int(seed), 7919, int(epoch)]).permutation(n).tolist()


def _save(obj, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def _write_json(path: Path, obj) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1, default=_json_default) + "\n")


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _write_csv(path: Path, rows: list[dict], columns: list[str]) -> None:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: _csv_value(r.get(k)) for k in columns})
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())


def _csv_value(v):
    if isinstance(v, float):
        return repr(v)  # round-trips exactly
    return "" if v is None else v


def _progress(total: int, desc: str, enabled: bool):
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit="batch",
        file=sys.stderr,
        disable=not enabled,
        leave=False,
        dynamic_ncols=True,
    )


# -- checkpoints -------------------------------------------------------------------------------------
def load_checkpoint(path: str | os.PathLike, *, input_mode: str | None = None) -> dict:
    """Read and check a checkpoint written by :func:`train`.

    Parameters
    ----------
    path : path-like
        ``last.pt`` or ``best.pt`` (a run folder is accepted and means its ``best.pt``).
    input_mode : str, optional
        The input mode the caller will feed; a checkpoint of another mode is refused.

    Returns
    -------
    dict
        The checkpoint (``config``, ``model_config``, ``model``, ``optimizer``, ``epoch``, ...).

    Raises
    ------
    FormatError
        Missing, unreadable or foreign file; weights that do not fit the stored configuration.
    ParameterError
        ``input_mode`` differs from the checkpoint's.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "best.pt"
    if not path.is_file():
        raise FormatError(f"{path}: no such checkpoint")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types (pickle, zip, runtime) for bad files
        raise FormatError(
            f"{path}: not a readable torch checkpoint ({type(exc).__name__})"
        ) from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise FormatError(f"{path}: not a sparsetools depth checkpoint")
    if int(ckpt.get("version", 0)) > CHECKPOINT_VERSION:
        raise FormatError(
            f"{path}: checkpoint version {ckpt['version']} is newer than this sparsetools"
        )
    mc = ckpt.get("model_config") or {}
    if input_mode is not None and mc.get("input_mode") != input_mode:
        raise ParameterError(
            f"{path} was trained with input mode '{mc.get('input_mode')}' "
            f"({INPUT_CHANNELS.get(mc.get('input_mode'), '?')} channels), not '{input_mode}'"
        )
    stem = ckpt.get("model", {}).get("stem.0.weight")
    expected = INPUT_CHANNELS.get(mc.get("input_mode"))
    if stem is None or expected is None or stem.shape[1] != expected:
        got = None if stem is None else int(stem.shape[1])
        raise FormatError(
            f"{path}: weights for {got} input channels do not match the stored input mode "
            f"'{mc.get('input_mode')}'"
        )
    ckpt["path"] = str(path)
    return ckpt


def _model_from_checkpoint(ckpt: dict) -> DepthCompletionUNet:
    model = build_model(ckpt["model_config"])
    try:
        model.load_state_dict(ckpt["model"])
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = first[1].strip() if len(first) > 1 else first[0]
        raise FormatError(f"{ckpt.get('path')}: weights do not fit the model ({detail})") from exc
    return model


# -- pictures --------------------------------------------------------------------------------------
def _nice_ticks(
    lo: float, hi: float, n: int = 5, *, integer: bool = False
) -> tuple[float, float, list[float]]:
    if not (math.isfinite(lo) and math.isfinite(hi)):
        lo, hi = 0.0, 1.0
    if hi - lo < 1e-12:
        pad = 1.0 if integer else (abs(hi) * 0.1 or 1.0)
        lo, hi = lo - pad, hi + pad
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    steps = (1, 2, 5, 10) if integer else (1, 2, 2.5, 5, 10)
    step = next(m * mag for m in steps if m * mag >= raw)
    if integer:
        step = max(step, 1)
    lo_t = math.floor(lo / step) * step
    hi_t = math.ceil(hi / step) * step
    ticks = [lo_t + i * step for i in range(round((hi_t - lo_t) / step) + 1)]
    return lo_t, hi_t, ticks


def _log_ticks(lo: float, hi: float) -> tuple[float, float, list[float]]:
    """Axis range and ticks (1, 2, 5 x 10^k) of a logarithmic axis covering [lo, hi] > 0."""
    k0, k1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    ticks = [m * 10.0**k for k in range(k0, k1 + 1) for m in (1, 2, 5)]
    y0 = max(t for t in ticks if t <= lo * (1 + 1e-9))
    y1 = min(t for t in ticks if t >= hi * (1 - 1e-9))
    return y0, y1, [t for t in ticks if y0 <= t <= y1]


def _fmt(v: float) -> str:
    return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.2e}"


def _plot_panel(
    series: list[tuple[str, list[float], list[float], tuple[int, int, int]]],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    size: tuple[int, int] = (440, 300),
    log: bool | None = None,
) -> np.ndarray:
    """One line plot; ``log`` = logarithmic y axis (default: when positive values span > 10x)."""
    import cv2

    w, h = size
    img = np.full((h, w, 3), 255, np.uint8)
    left, right, top, bottom = 66, 14, 30, 44
    font = cv2.FONT_HERSHEY_SIMPLEX
    xs_all = [x for _, xs, _, _ in series for x in xs]
    ys_all = [y for _, _, ys, _ in series for y in ys if math.isfinite(y)]
    x0, x1, xt = _nice_ticks(min(xs_all, default=0), max(xs_all, default=1), integer=True)
    lo, hi = min(ys_all, default=0.0), max(ys_all, default=1.0)
    if log is None:
        log = lo > 0 and hi / lo > 10
    if log and lo > 0:
        y0, y1, yt = _log_ticks(lo, hi)
        fy = math.log10
        ylabel = f"{ylabel}, log"
    else:
        y0, y1, yt = _nice_ticks(lo, hi)
        fy = float

    def px(x, y):
        u = left + (x - x0) / (x1 - x0) * (w - left - right)
        v = h - bottom - (fy(y) - fy(y0)) / (fy(y1) - fy(y0)) * (h - top - bottom)
        return round(u), round(v)

    grey, black = (225, 225, 225), (0, 0, 0)
    for t in yt:
        _, v = px(x0, t)
        cv2.line(img, (left, v), (w - right, v), grey, 1)
        label = _fmt(t)
        (tw, _), _ = cv2.getTextSize(label, font, 0.38, 1)
        cv2.putText(img, label, (left - 5 - tw, v + 4), font, 0.38, black, 1, cv2.LINE_AA)
    for t in xt:
        u, _ = px(t, y0)
        cv2.line(img, (u, top), (u, h - bottom), grey, 1)
        label = _fmt(t)
        (tw, _), _ = cv2.getTextSize(label, font, 0.38, 1)
        cv2.putText(img, label, (u - tw // 2, h - bottom + 16), font, 0.38, black, 1, cv2.LINE_AA)
    cv2.line(img, (left, top), (left, h - bottom), black, 1)
    cv2.line(img, (left, h - bottom), (w - right, h - bottom), black, 1)
    cv2.putText(img, title, (left, 20), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, xlabel, (w // 2 - 4 * len(xlabel), h - 8), font, 0.42, black, 1, cv2.LINE_AA)
    # y label written horizontally then rotated
    lab = np.full((18, 8 * len(ylabel) + 8, 3), 255, np.uint8)
    cv2.putText(lab, ylabel, (2, 13), font, 0.42, black, 1, cv2.LINE_AA)
    lab = np.rot90(lab)
    y_start = max(top, (h - lab.shape[0]) // 2)
    if y_start + lab.shape[0] <= h and lab.shape[1] <= left:
        img[y_start : y_start + lab.shape[0], 0 : lab.shape[1]] = np.minimum(
            img[y_start : y_start + lab.shape[0], 0 : lab.shape[1]], lab
        )
    for k, (name, xs, ys, colour) in enumerate(series):
        pts = [px(x, y) for x, y in zip(xs, ys, strict=True) if math.isfinite(y)]
        bgr = colour[::-1]
        if len(pts) > 1:
            cv2.polylines(img, [np.array(pts, np.int32)], False, bgr, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 3, bgr, -1, cv2.LINE_AA)
        ly = top + 14 + 16 * k
        cv2.line(img, (w - right - 110, ly - 4), (w - right - 90, ly - 4), bgr, 2)
        cv2.putText(img, name, (w - right - 86, ly), font, 0.4, black, 1, cv2.LINE_AA)
    return img[:, :, ::-1].copy()


def draw_curves(history: list[dict], *, loss_name: str = "loss") -> np.ndarray:
    """Loss (train, validation) and validation RMSE per epoch, as an (H, W, 3) uint8 RGB image."""
    from ..ops.colormap import side_by_side

    ep = [float(r["epoch"]) for r in history]
    loss_panel = _plot_panel(
        [
            ("train", ep, [float(r["train_loss"]) for r in history], (31, 119, 180)),
            ("validation", ep, [float(r["val_loss"]) for r in history], (255, 127, 14)),
        ],
        title=f"{loss_name} loss",
        xlabel="epoch",
        ylabel="loss",
    )
    rmse_panel = _plot_panel(
        [("validation", ep, [float(r["rmse"]) for r in history], (44, 160, 44))],
        title="validation RMSE",
        xlabel="epoch",
        ylabel="RMSE (m)",
    )
    return side_by_side([loss_panel, rmse_panel], vertical=False, gap=6)


def prediction_picture(
    rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    *,
    max_depth: float = 80.0,
    min_panel_width: int = 240,
) -> np.ndarray:
    """One row per sample: rgb | sparse over rgb | prediction | gt, depth coloured 0-max m.

    Parameters
    ----------
    rows : list of (rgb (H, W, 3) uint8, sparse (H, W), prediction (H, W), gt (H, W))
    max_depth : float, metres
        Depth of the red end of the colour map (blue = 0 m).
    min_panel_width : int
        Small images are enlarged (nearest neighbour, integer factor) to at least this width.

    Returns
    -------
    (H', W', 3) uint8 RGB, with a header naming the columns.
    """
    import cv2

    from ..ops.colormap import colorize_depth, overlay_depth, side_by_side

    if not rows:
        raise ParameterError("no samples to draw")
    factor = max(1, math.ceil(min_panel_width / rows[0][0].shape[1]))

    def big(img):
        if factor == 1:
            return img
        return cv2.resize(img, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST)

    out = []
    for rgb, sparse, pred, gt in rows:
        panels = [
            rgb,
            overlay_depth(rgb, sparse, max_depth=max_depth, dilate=1),
            colorize_depth(pred, max_depth=max_depth),
            colorize_depth(gt, max_depth=max_depth),
        ]
        out.append(side_by_side([big(p) for p in panels], vertical=False, gap=4))
    body = side_by_side(out, vertical=True, gap=4)
    header = np.full((20, body.shape[1], 3), 255, np.uint8)
    panel_w = rows[0][0].shape[1] * factor
    names = ("rgb", "sparse depth", "prediction", f"ground truth (0-{max_depth:g} m)")
    for k, name in enumerate(names):
        cv2.putText(
            header,
            name,
            (k * (panel_w + 4) + 4, 14),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return np.concatenate([header, body], axis=0)


# -- evaluation core ---------------------------------------------------------------------------------
def _loader(dataset, *, batch_size: int, order: list[int] | None, workers: int, seed: int):
    from torch.utils.data import DataLoader

    return DataLoader(
        dataset,
        batch_size=batch_size,
        sampler=order if order is not None else list(range(len(dataset))),
        num_workers=workers,
        collate_fn=collate_samples,
        worker_init_fn=_worker_init if workers else None,
        generator=torch.Generator().manual_seed(int(seed)),
        persistent_workers=False,
    )


def _batches(loader):
    """Iterate a DataLoader; an error raised in a worker process keeps its one-line message.

    torch re-raises a worker's exception with the worker's formatted traceback as the message;
    the user should see only the original message, as with ``workers=0``.
    """
    try:
        yield from loader
    except SparsetoolsError as exc:
        text = str(exc)
        if "DataLoader worker" not in text:
            raise
        last = [line for line in text.splitlines() if line.strip()][-1]
        name = type(exc).__name__
        message = last.split(f"{name}: ", 1)[1] if f"{name}: " in last else last
        raise type(exc)(message) from None


def _eval_batch_size(dataset: DepthDataset, batch_size: int) -> int:
    # Images of several sizes cannot share a batch: evaluate them one by one.
    return batch_size if len(dataset.output_sizes()) == 1 else 1


@torch.no_grad()
def _run_evaluation(
    model: DepthCompletionUNet,
    dataset: DepthDataset,
    *,
    device: torch.device,
    batch_size: int,
    workers: int,
    loss: str | None,
    metric_kw: dict,
    max_depth: float = 80.0,
    picture_indices: tuple[int, ...] = (),
    progress: bool = False,
    desc: str = "eval",
) -> tuple[list[dict], float, list]:
    """Per-image metrics (with ids), mean loss, and picture rows of ``picture_indices``."""
    model.eval()
    per_image, pics = [], []
    loss_sum, n_loss = 0.0, 0
    loader = _loader(
        dataset,
        batch_size=_eval_batch_size(dataset, batch_size),
        order=None,
        workers=workers,
        seed=0,
    )
    with _progress(len(loader), desc, progress) as bar:
        for batch in _batches(loader):
            rgb = batch["rgb"].to(device)
            sparse = batch["sparse"].to(device)
            gt = batch["gt"].to(device)
            pred = model(model_inputs(rgb, sparse, model.input_mode))
            if loss is not None:
                loss_sum += float(depth_loss(loss, pred, _cap(gt, max_depth))) * len(rgb)
                n_loss += len(rgb)
            pred_np = pred[:, 0].float().cpu().numpy()
            gt_np = batch["gt"][:, 0].numpy()
            for k, idx in enumerate(batch["index"].tolist()):
                m = depth_metrics(pred_np[k], gt_np[k], **metric_kw)
                per_image.append({"id": dataset.sample_id(idx), **m})
                if idx in picture_indices:
                    rgb_u8 = np.clip(batch["rgb"][k].permute(1, 2, 0).numpy() * 255 + 0.5, 0, 255)
                    pics.append(
                        (
                            rgb_u8.astype(np.uint8),
                            batch["sparse"][k, 0].numpy(),
                            pred_np[k],
                            gt_np[k],
                        )
                    )
            bar.update(1)
    return per_image, (loss_sum / n_loss if n_loss else math.nan), pics


def _cap(gt: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Ground truth beyond ``max_depth`` becomes 0 (not used by the losses, as by the metrics)."""
    return torch.where(gt < max_depth, gt, torch.zeros_like(gt))


# -- training ----------------------------------------------------------------------------------------
def _check_run_dir(out: Path, dataset: Path, resume: bool) -> None:
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} exists and is not a folder")
    try:
        if out.resolve() == dataset.resolve() or dataset.resolve() in out.resolve().parents:
            raise OutputError(f"run folder {out} is inside the dataset {dataset}: choose another")
    except OSError:  # pragma: no cover - unresolvable paths are reported later
        pass
    if resume:
        if not (out / "last.pt").is_file():
            raise ParameterError(f"nothing to resume: {out / 'last.pt'} does not exist")
        return
    present = [n for n in RUN_FILES if (out / n).exists()]
    if present:
        raise OutputError(
            f"{out} already holds a run ({', '.join(present)}): use --resume to continue it "
            "or choose another folder"
        )


def _resumed_config(config: TrainConfig, ckpt: dict, explicit: set[str] | None) -> TrainConfig:
    """The checkpoint's configuration, with the fields that may change taken from ``config``."""
    saved = TrainConfig.from_dict(ckpt["config"])
    mine = config.to_dict()
    theirs = saved.to_dict()
    check = explicit if explicit is not None else set(mine) - set(TrainConfig.RESUMABLE)
    for name in sorted(check):
        if name in TrainConfig.RESUMABLE or name in ("dataset", "out_dir") or name not in theirs:
            continue
        if mine[name] != theirs[name]:
            if name == "input_mode":
                raise ParameterError(
                    f"the run in {config.out_dir} was trained with input mode "
                    f"'{theirs[name]}', not '{mine[name]}': a checkpoint cannot change its "
                    "input mode"
                )
            raise ParameterError(
                f"--resume continues the run's own settings: {name} is {theirs[name]!r} "
                f"there, not {mine[name]!r}"
            )
    for name in TrainConfig.RESUMABLE:
        setattr(saved, name, getattr(config, name))
    saved.dataset = config.dataset
    saved.out_dir = config.out_dir
    return saved


def epoch_lr(config: TrainConfig, epoch: int) -> float:
    """Learning rate of (0-based) ``epoch``: a pure function of the configuration and epoch.

    ``constant``: ``lr``; ``step``: ``lr * lr_gamma ** (epoch // lr_step)`` (Ma & Karaman);
    ``cosine``: from ``lr`` down to ``lr / 100`` over ``epochs`` (so a resumed run with a larger
    ``epochs`` follows a new, longer schedule).
    """
    if config.lr_schedule == "step":
        return config.lr * config.lr_gamma ** (epoch // config.lr_step)
    if config.lr_schedule == "cosine":
        t = min(epoch / max(config.epochs - 1, 1), 1.0)
        return config.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))
    return config.lr


def _make_optimizer(model, config: TrainConfig):
    if config.optimizer == "adam":
        return torch.optim.Adam(model.parameters(), lr=config.lr)
    return torch.optim.SGD(model.parameters(), lr=config.lr, momentum=0.9, weight_decay=1e-4)


def _picture_indices(n: int, k: int) -> tuple[int, ...]:
    if k <= 0 or n == 0:
        return ()
    return tuple(sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(min(k, n))}))


def train(
    config: TrainConfig,
    *,
    resume: bool = False,
    progress: bool = False,
    explicit: set[str] | None = None,
    on_epoch: Callable[[dict], None] | None = None,
) -> dict:
    """Train the early-fusion U-Net on a sparsetools dataset.

    Parameters
    ----------
    config : TrainConfig
    resume : bool
        Continue the run in ``config.out_dir`` from its ``last.pt``; its saved configuration
        is used except for :attr:`TrainConfig.RESUMABLE` fields (``epochs``, ``max_steps``,
        ``workers``, ``device``, ``threads``, ``pictures``).
    progress : bool
        A tqdm bar per epoch on stderr (loss and samples/s).
    explicit : set of str, optional
        Names of the fields the user set explicitly; when resuming, only those are compared
        with the saved configuration (default: every field that is not resumable).
    on_epoch : callable, optional
        Called with each epoch's metrics row.

    Returns
    -------
    dict
        Summary: run folder, epochs and steps done, best epoch and its validation metrics,
        the last epoch's metrics, seconds.

    Raises
    ------
    ParameterError, FormatError, OutputError
        Bad settings, a split without ground truth, an empty split, mixed image sizes without
        ``crop``, an existing run without ``resume``, a diverged loss.
    """
    config.validate()
    out = Path(config.out_dir)
    dataset_path = Path(config.dataset)
    _check_run_dir(out, dataset_path, resume)
    ckpt = None
    if resume:
        ckpt = load_checkpoint(out / "last.pt")
        config = _resumed_config(config, ckpt, explicit)
        config.validate()
    device = _device(config.device)

    train_set = DepthDataset(
        config.dataset,
        config.train_split,
        augment=True,
        crop=config.crop,
        seed=config.seed,
        scale_range=config.scale_range,
        jitter=config.jitter,
    )
    val_set = DepthDataset(config.dataset, config.val_split, augment=False)
    sizes = train_set.output_sizes()
    if len(sizes) > 1:
        listed = ", ".join(f"{h}x{w}" for h, w in sorted(sizes)[:4])
        raise ParameterError(
            f"split '{config.train_split}' mixes image sizes ({listed}, HxW): images of one "
            "batch must have one size; use --crop HxW"
        )
    ((h, w),) = sizes
    if math.ceil(h / STRIDE) * math.ceil(w / STRIDE) == 1 and config.batch_size < 2:
        raise ParameterError("images of at most 16x16 pixels need --batch-size >= 2 (batch norm)")

    started = time.perf_counter()
    with _torch_settings(config.threads, device):
        torch.manual_seed(config.seed)
        model = DepthCompletionUNet(
            config.input_mode, width=config.width, final_layer=config.final_layer
        ).to(device)
        optimizer = _make_optimizer(model, config)
        history: list[dict] = []
        epoch, batch_in_epoch, step = 0, 0, 0
        epoch_loss_sum, epoch_samples, epoch_seconds = 0.0, 0, 0.0
        best = {"rmse": math.inf, "epoch": None}
        if ckpt is not None:
            model.load_state_dict(ckpt["model"])
            optimizer.load_state_dict(ckpt["optimizer"])
            torch.set_rng_state(ckpt["rng"]["torch"])
            history = list(ckpt["history"])
            epoch, batch_in_epoch, step = ckpt["epoch"], ckpt["batch_in_epoch"], ckpt["step"]
            epoch_loss_sum = float(ckpt["epoch_loss_sum"])
            epoch_samples = int(ckpt["epoch_samples"])
            epoch_seconds = float(ckpt.get("epoch_seconds", 0.0))
            best = dict(ckpt["best"])
        else:
            out.mkdir(parents=True, exist_ok=True)
        _write_json(out / "config.json", config.to_dict())

        n_train = len(train_set)
        batches_per_epoch = math.ceil(n_train / config.batch_size)
        pics = _picture_indices(len(val_set), config.pictures)
        metric_kw = {"max_depth": config.max_depth}
        last_row = history[-1] if history else None

        while epoch < config.epochs and (config.max_steps is None or step < config.max_steps):
            train_set.set_epoch(epoch)
            order = _epoch_order(config.seed, epoch, n_train)
            skip = batch_in_epoch * config.batch_size
            todo = order[skip:]
            if config.max_steps is not None:
                todo = todo[: (config.max_steps - step) * config.batch_size]
            # a trailing batch of one sample at the 1x1 bottleneck would break batch norm
            if (
                math.ceil(h / STRIDE) * math.ceil(w / STRIDE) == 1
                and len(todo) % config.batch_size == 1
            ):
                todo = todo[:-1]
            loader = _loader(
                train_set,
                batch_size=config.batch_size,
                order=todo,
                workers=config.workers,
                seed=config.seed + epoch,
            )
            for group in optimizer.param_groups:
                group["lr"] = epoch_lr(config, epoch)
            model.train()
            t0 = time.perf_counter()
            with _progress(
                batches_per_epoch, f"epoch {epoch + 1}/{config.epochs}", progress
            ) as bar:
                bar.update(batch_in_epoch)
                for batch in _batches(loader):
                    rgb = batch["rgb"].to(device)
                    sparse = batch["sparse"].to(device)
                    gt = _cap(batch["gt"].to(device), config.max_depth)
                    pred = model(model_inputs(rgb, sparse, config.input_mode))
                    loss = depth_loss(config.loss, pred, gt)
                    if not torch.isfinite(loss):
                        raise ParameterError(
                            f"training diverged: {config.loss} loss is {float(loss.detach())} at step "
                            f"{step + 1}; lower --lr"
                        )
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    optimizer.step()
                    step += 1
                    batch_in_epoch += 1
                    epoch_loss_sum += float(loss.detach()) * len(rgb)
                    epoch_samples += len(rgb)
                    elapsed = epoch_seconds + time.perf_counter() - t0
                    bar.set_postfix(
                        loss=f"{epoch_loss_sum / epoch_samples:.4g}",
                        img_s=f"{epoch_samples / max(elapsed, 1e-9):.1f}",
                    )
                    bar.update(1)
            epoch_seconds += time.perf_counter() - t0
            complete = batch_in_epoch >= batches_per_epoch

            per_image, val_loss, pic_rows = _run_evaluation(
                model,
                val_set,
                device=device,
                batch_size=config.batch_size,
                workers=config.workers,
                loss=config.loss,
                metric_kw=metric_kw,
                max_depth=config.max_depth,
                picture_indices=pics,
                progress=progress,
                desc="validation",
            )
            val = aggregate_metrics(per_image)
            row = {
                "epoch": epoch + 1,
                "step": step,
                "batches": batch_in_epoch,
                "complete": int(complete),
                "train_loss": epoch_loss_sum / max(epoch_samples, 1),
                "val_loss": val_loss,
                **{k: val[k] for k in METRIC_NAMES},
                "val_images": val["n_images"],
                "lr": optimizer.param_groups[0]["lr"],
                "seconds": round(epoch_seconds, 3),
                "samples_per_s": round(epoch_samples / max(epoch_seconds, 1e-9), 3),
            }
            # a partial epoch's row is replaced when the epoch is finished after --resume
            history = [r for r in history if r["epoch"] != row["epoch"]] + [row]
            improved = val["rmse"] < best["rmse"]
            if improved:
                best = {"rmse": val["rmse"], "epoch": epoch + 1, "metrics": row}
            if complete:
                epoch += 1
                batch_in_epoch, epoch_loss_sum, epoch_samples, epoch_seconds = 0, 0.0, 0, 0.0
            state = {
                "format": CHECKPOINT_FORMAT,
                "version": CHECKPOINT_VERSION,
                "config": config.to_dict(),
                "model_config": model.config(),
                "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
                "optimizer": optimizer.state_dict(),
                "epoch": epoch,
                "batch_in_epoch": batch_in_epoch,
                "step": step,
                "epoch_loss_sum": epoch_loss_sum,
                "epoch_samples": epoch_samples,
                "epoch_seconds": epoch_seconds,
                "best": best,
                "best_metric": {"name": "rmse", "value": best["rmse"], "epoch": best["epoch"]},
                "history": history,
                "val_metrics": row,
                "rng": {"torch": torch.get_rng_state()},
            }
            if improved:
                _save(state, out / "best.pt")
            _save(state, out / "last.pt")
            columns = list(row)
            _write_csv(out / "metrics.csv", history, columns)
            _write_png(out / "curves.png", draw_curves(history, loss_name=config.loss))
            if pic_rows:
                _write_png(
                    out / "predictions" / f"epoch_{row['epoch']:03d}.png",
                    prediction_picture(pic_rows, max_depth=config.max_depth),
                )
            last_row = row
            log.info(
                "epoch %d: train loss %.4g, val RMSE %.4g m",
                row["epoch"],
                row["train_loss"],
                row["rmse"],
            )
            if on_epoch is not None:
                on_epoch(row)

    return {
        "run_dir": str(out),
        "input_mode": config.input_mode,
        "epochs_done": epoch,
        "steps": step,
        "best_epoch": best["epoch"],
        "best_rmse": best["rmse"],
        "last": last_row,
        "seconds": round(time.perf_counter() - started, 2),
    }


def _write_png(path: Path, rgb: np.ndarray) -> None:
    from ..io.image import write_image

    write_image(path, rgb)


# -- evaluation ----------------------------------------------------------------------------------------
def evaluate_checkpoint(
    checkpoint: str | os.PathLike,
    dataset: str | os.PathLike,
    *,
    split: str = "test",
    garg_crop: bool = False,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    device: str = "cpu",
    batch_size: int = 4,
    workers: int = 0,
    input_mode: str | None = None,
    progress: bool = False,
) -> dict:
    """Metrics of a trained model on one split of a dataset.

    Returns
    -------
    dict
        ``metrics`` (averaged, :func:`~sparsetools.ops.metrics.aggregate_metrics`),
        ``per_image`` (list of dicts with ``id``), and the settings used.
    """
    ckpt = load_checkpoint(checkpoint, input_mode=input_mode)
    dev = _device(device)
    model = _model_from_checkpoint(ckpt).to(dev)
    data = DepthDataset(dataset, split, augment=False)
    with _torch_settings(None, dev):
        per_image, _, _ = _run_evaluation(
            model,
            data,
            device=dev,
            batch_size=batch_size,
            workers=workers,
            loss=None,
            metric_kw={"min_depth": min_depth, "max_depth": max_depth, "garg_crop": garg_crop},
            progress=progress,
        )
    return {
        "metrics": aggregate_metrics(per_image),
        "per_image": per_image,
        "checkpoint": ckpt["path"],
        "input_mode": ckpt["model_config"]["input_mode"],
        "epoch": ckpt.get("epoch"),
        "dataset": str(dataset),
        "split": split,
        "garg_crop": garg_crop,
        "min_depth": min_depth,
        "max_depth": max_depth,
    }


_DEPTH_SUFFIXES = (".png", ".npy")


def _depth_files(folder: Path, what: str) -> dict[str, Path]:
    if not folder.is_dir():
        raise FormatError(f"{folder}: no such {what} folder")
    files: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in _DEPTH_SUFFIXES and not p.name.startswith("."):
            if p.stem in files:
                raise FormatError(f"{folder}: two {what} files for '{p.stem}'")
            files[p.stem] = p
    if not files:
        raise FormatError(f"{folder}: no depth PNG or .npy files ({what})")
    return files


def evaluate_folders(
    pred_dir: str | os.PathLike,
    gt_dir: str | os.PathLike,
    *,
    garg_crop: bool = False,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    progress: bool = False,
) -> dict:
    """Metrics of any method's predictions: depth files matched by stem.

    Parameters
    ----------
    pred_dir, gt_dir : path-like
        Folders of KITTI uint16 depth PNGs (or ``.npy`` metres); files are matched by stem.
        Every ground-truth file needs a prediction; predictions without ground truth are
        ignored (and counted).

    Raises
    ------
    FormatError
        A missing prediction, unreadable files, or a prediction of another size than its
        ground truth.
    """
    from ..io.dataset import read_depth_file

    preds = _depth_files(Path(pred_dir), "prediction")
    gts = _depth_files(Path(gt_dir), "ground-truth")
    missing = sorted(set(gts) - set(preds))
    if missing:
        raise FormatError(
            f"{len(missing)} of {len(gts)} ground-truth file(s) have no prediction in "
            f"{pred_dir} (e.g. '{missing[0]}')"
        )
    per_image = []
    with _progress(len(gts), "eval", progress) as bar:
        for stem, gt_path in gts.items():
            gt = read_depth_file(gt_path)
            pred = read_depth_file(preds[stem])
            if pred.shape != gt.shape:
                raise FormatError(
                    f"'{stem}': prediction is {pred.shape[1]}x{pred.shape[0]}, ground truth "
                    f"{gt.shape[1]}x{gt.shape[0]}"
                )
            m = depth_metrics(
                pred, gt, min_depth=min_depth, max_depth=max_depth, garg_crop=garg_crop
            )
            per_image.append({"id": stem, **m})
            bar.update(1)
    return {
        "metrics": aggregate_metrics(per_image),
        "per_image": per_image,
        "pred_dir": str(pred_dir),
        "gt_dir": str(gt_dir),
        "unmatched_predictions": len(set(preds) - set(gts)),
        "garg_crop": garg_crop,
        "min_depth": min_depth,
        "max_depth": max_depth,
    }


def write_eval_results(result: dict, path: str | os.PathLike) -> list[Path]:
    """Write an evaluation as JSON and CSV (per image plus a ``mean`` row), atomically.

    ``path`` ending in ``.json`` or ``.csv`` names that file and its sibling with the other
    suffix; any other path is used as the stem. Returns the files written.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix.lower() in (".json", ".csv") else path
    json_path, csv_path = stem.with_suffix(".json"), stem.with_suffix(".csv")
    _write_json(json_path, result)
    columns = ["id", *METRIC_NAMES, "n_pixels"]
    mean_row = {
        "id": "mean",
        **{k: result["metrics"][k] for k in METRIC_NAMES},
        "n_pixels": result["metrics"]["n_pixels"],
    }
    _write_csv(csv_path, [*result["per_image"], mean_row], columns)
    return [json_path, csv_path]
