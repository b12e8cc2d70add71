"""Evaluation: depth metrics of a checkpoint on a dataset split, or of any method's depth files.

- :func:`run_evaluation` is the core that training (validation after every epoch) and
  :func:`evaluate_checkpoint` share: per-image metrics (:func:`sparsetools.ops.metrics.depth_metrics`),
  the mean loss, and picture rows.
- :func:`evaluate_checkpoint` evaluates a supervised or self-supervised checkpoint.
  Self-supervised camera-only models are scale-ambiguous: they are evaluated with per-image
  median scaling (monodepth2's protocol), and the result says so (``median_scaling``);
  models trained with the sparse-LiDAR loss, and supervised models, are evaluated without any
  scaling. For a self-supervised checkpoint on a split whose manifest has true camera poses,
  the pose network is evaluated too (ATE over 5-frame snippets,
  :mod:`sparsetools.train.selfsup.pose_eval`).
- :func:`evaluate_folders` scores depth PNG / ``.npy`` files matched by stem.
- :func:`write_eval_results` writes a result as JSON and CSV.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..errors import FormatError
from ..ops.metrics import METRIC_NAMES, aggregate_metrics, depth_metrics, format_metrics_table
from .checkpoint import load_checkpoint, model_from_checkpoint
from .data import DepthDataset, collate_samples
from .losses import depth_loss
from .model import DepthCompletionUNet
from .runtime import (
    batches,
    make_loader,
    progress_bar,
    resolve_device,
    torch_settings,
    write_csv,
    write_json,
)

if TYPE_CHECKING:
    from .selfsup.pose_eval import PoseAccuracy

__all__ = [
    "EvalResult",
    "EvaluationPass",
    "cap_depth",
    "evaluate_checkpoint",
    "evaluate_folders",
    "format_eval_text",
    "picture_indices",
    "run_evaluation",
    "write_eval_results",
]


@dataclass(frozen=True)
class EvaluationPass:
    """What one pass over a split gives: per-image metrics (with ``id``), mean loss, pictures.

    ``pictures`` are (rgb (H, W, 3) uint8, sparse (H, W), prediction (H, W), gt (H, W)) rows
    for :func:`sparsetools.train.plots.prediction_picture`; ``loss`` is NaN when not computed.
    """

    per_image: list[dict]
    loss: float
    pictures: list[tuple]


@dataclass(frozen=True)
class EvalResult:
    """An evaluation: averaged and per-image metrics, the protocol, and what was evaluated.

    ``median_scaling`` is True when each prediction was scaled by median(gt) / median(pred)
    before the metrics (camera-only self-supervised models); the per-image rows then hold the
    ``scale``. Fields of the other kind of evaluation (checkpoint vs folders) are None.
    """

    metrics: dict
    per_image: list[dict]
    garg_crop: bool
    min_depth: float
    max_depth: float
    median_scaling: bool = False
    checkpoint: str | None = None
    kind: str | None = None
    input_mode: str | None = None
    lidar_encoder: str | None = None
    epoch: int | None = None
    dataset: str | None = None
    split: str | None = None
    pred_dir: str | None = None
    gt_dir: str | None = None
    unmatched_predictions: int | None = None
    pose: PoseAccuracy | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict (fields that do not apply are left out)."""
        out = {}
        for k, v in asdict(self).items():
            if v is None and k not in ("epoch",):
                continue
            out[k] = v
        if self.checkpoint is None:
            out.pop("epoch", None)
        return out


def cap_depth(gt: torch.Tensor, max_depth: float) -> torch.Tensor:
    """Depth at or beyond ``max_depth`` becomes 0 (unused by the losses, as by the metrics)."""
    return torch.where(gt < max_depth, gt, torch.zeros_like(gt))


def picture_indices(n: int, k: int) -> tuple[int, ...]:
    """``k`` sample positions spread evenly over ``0..n-1`` (first and last included)."""
    if k <= 0 or n == 0:
        return ()
    return tuple(sorted({round(i * (n - 1) / max(k - 1, 1)) for i in range(min(k, n))}))


def eval_batch_size(sizes: set[tuple[int, int]], batch_size: int) -> int:
    """Images of several sizes cannot share a batch: evaluate them one by one."""
    return batch_size if len(sizes) == 1 else 1


def rgb_uint8(rgb: torch.Tensor) -> np.ndarray:
    """(3, H, W) float 0..1 tensor -> (H, W, 3) uint8."""
    return np.clip(rgb.permute(1, 2, 0).numpy() * 255 + 0.5, 0, 255).astype(np.uint8)


@torch.no_grad()
def run_evaluation(
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
) -> EvaluationPass:
    """Per-image metrics of ``model`` over ``dataset``, its mean ``loss``, and pictures.

    Parameters
    ----------
    metric_kw : dict
        Keyword arguments of :func:`~sparsetools.ops.metrics.depth_metrics` (``min_depth``,
        ``max_depth``, ``garg_crop``, ``median_scaling``).
    max_depth : float, metres
        Ground truth at or beyond it is not used by the loss.
    """
    model.eval()
    per_image, pics = [], []
    loss_sum, n_loss = 0.0, 0
    loader = make_loader(
        dataset,
        batch_size=eval_batch_size(dataset.output_sizes(), batch_size),
        order=None,
        workers=workers,
        seed=0,
        collate=collate_samples,
    )
    with progress_bar(len(loader), desc, progress) as bar:
        for batch in batches(loader):
            rgb = batch["rgb"].to(device)
            sparse = batch["sparse"].to(device)
            gt = batch["gt"].to(device)
            pred = model.depth_of(rgb, sparse)
            if loss is not None:
                loss_sum += float(depth_loss(loss, pred, cap_depth(gt, max_depth))) * len(rgb)
                n_loss += len(rgb)
            pred_np = pred[:, 0].float().cpu().numpy()
            gt_np = batch["gt"][:, 0].numpy()
            for k, idx in enumerate(batch["index"].tolist()):
                m = depth_metrics(pred_np[k], gt_np[k], **metric_kw)
                per_image.append({"id": dataset.sample_id(idx), **m})
                if idx in picture_indices:
                    scale = m.get("scale", 1.0)
                    shown = pred_np[k] * (scale if math.isfinite(scale) else 1.0)
                    pics.append(
                        (rgb_uint8(batch["rgb"][k]), batch["sparse"][k, 0].numpy(), shown, gt_np[k])
                    )
            bar.update(1)
    return EvaluationPass(per_image, (loss_sum / n_loss if n_loss else math.nan), pics)


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
    median_scaling: bool | None = None,
    pose: bool = True,
    progress: bool = False,
) -> EvalResult:
    """Metrics of a trained model on one split of a dataset.

    Parameters
    ----------
    checkpoint : path-like
        ``best.pt`` / ``last.pt`` (or the run folder: its ``best.pt``).
    dataset : path-like
    split : str
    garg_crop : bool
        Evaluate inside the Garg crop only.
    min_depth, max_depth : float, metres
        Ground-truth range evaluated.
    median_scaling : bool, optional
        Per-image median scaling. Default (None): on for camera-only self-supervised models
        (trained without the sparse loss), off for every other model.
    pose : bool
        Also evaluate the pose network of a self-supervised model when the split's manifest
        has true poses (``T_world_cam``).

    Returns
    -------
    EvalResult
    """
    ckpt = load_checkpoint(checkpoint, input_mode=input_mode)
    dev = resolve_device(device)
    model = model_from_checkpoint(ckpt).to(dev)
    selfsup = ckpt.config.selfsup
    if median_scaling is None:
        median_scaling = selfsup is not None and not selfsup.metric_scale
    data = DepthDataset(dataset, split, augment=False)
    with torch_settings(None, dev):
        result = run_evaluation(
            model,
            data,
            device=dev,
            batch_size=batch_size,
            workers=workers,
            loss=None,
            metric_kw={
                "min_depth": min_depth,
                "max_depth": max_depth,
                "garg_crop": garg_crop,
                "median_scaling": bool(median_scaling),
            },
            progress=progress,
        )
        pose_accuracy = None
        if pose and ckpt.kind == "self-supervised":
            from .checkpoint import pose_from_checkpoint
            from .selfsup.pose_eval import evaluate_pose

            pose_accuracy = evaluate_pose(
                pose_from_checkpoint(ckpt).to(dev), dataset, split=split, device=dev
            )
    return EvalResult(
        metrics=aggregate_metrics(result.per_image),
        per_image=result.per_image,
        garg_crop=garg_crop,
        min_depth=min_depth,
        max_depth=max_depth,
        median_scaling=bool(median_scaling),
        checkpoint=str(ckpt.path),
        kind=ckpt.kind,
        input_mode=ckpt.input_mode,
        lidar_encoder=ckpt.lidar_encoder,
        epoch=ckpt.state.epoch,
        dataset=str(dataset),
        split=split,
        pose=pose_accuracy,
    )


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
    median_scaling: bool = False,
    progress: bool = False,
) -> EvalResult:
    """Metrics of any method's predictions: depth files matched by stem.

    Parameters
    ----------
    pred_dir, gt_dir : path-like
        Folders of KITTI uint16 depth PNGs (or ``.npy`` metres); files are matched by stem.
        Every ground-truth file needs a prediction; predictions without ground truth are
        ignored (and counted).
    median_scaling : bool
        Per-image median scaling (for scale-ambiguous monocular methods).

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
    with progress_bar(len(gts), "eval", progress) as bar:
        for stem, gt_path in gts.items():
            gt = read_depth_file(gt_path)
            pred = read_depth_file(preds[stem])
            if pred.shape != gt.shape:
                raise FormatError(
                    f"'{stem}': prediction is {pred.shape[1]}x{pred.shape[0]}, ground truth "
                    f"{gt.shape[1]}x{gt.shape[0]}"
                )
            m = depth_metrics(
                pred,
                gt,
                min_depth=min_depth,
                max_depth=max_depth,
                garg_crop=garg_crop,
                median_scaling=median_scaling,
            )
            per_image.append({"id": stem, **m})
            bar.update(1)
    return EvalResult(
        metrics=aggregate_metrics(per_image),
        per_image=per_image,
        garg_crop=garg_crop,
        min_depth=min_depth,
        max_depth=max_depth,
        median_scaling=median_scaling,
        pred_dir=str(pred_dir),
        gt_dir=str(gt_dir),
        unmatched_predictions=len(set(preds) - set(gts)),
    )


def format_eval_text(result: EvalResult, *, title: str = "") -> str:
    """The metrics table of a result, with the scaling protocol and the pose accuracy."""
    lines = [format_metrics_table(result.metrics, title=title)]
    if result.median_scaling:
        scales = [r["scale"] for r in result.per_image if math.isfinite(r.get("scale", math.nan))]
        med = float(np.median(scales)) if scales else math.nan
        lines.append(
            f"{'scaling':<13} per-image median (monodepth2 protocol; median scale {med:.4g})"
        )
    elif result.kind == "self-supervised":
        lines.append(f"{'scaling':<13} none (metric scale from the sparse loss)")
    if result.pose is not None:
        p = result.pose
        lines.append(
            f"{'pose ATE':<13} {p.ate_mean:>10.4f} m  +- {p.ate_std:.4f} "
            f"({p.n_snippets} snippets of {p.snippet_length} frames)"
        )
    return "\n".join(lines)


def write_eval_results(result: EvalResult, path: str | os.PathLike) -> list[Path]:
    """Write an evaluation as JSON and CSV (per image plus a ``mean`` row), atomically.

    ``path`` ending in ``.json`` or ``.csv`` names that file and its sibling with the other
    suffix; any other path is used as the stem. Returns the files written.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix.lower() in (".json", ".csv") else path
    json_path, csv_path = stem.with_suffix(".json"), stem.with_suffix(".csv")
    write_json(json_path, result.to_dict())
    extra = ["scale"] if result.median_scaling else []
    columns = ["id", *METRIC_NAMES, "n_pixels", *extra]
    mean_row = {
        "id": "mean",
        **{k: result.metrics[k] for k in METRIC_NAMES},
        "n_pixels": result.metrics["n_pixels"],
    }
    write_csv(csv_path, [*result.per_image, mean_row], columns)
    return [json_path, csv_path]
