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
- :func:`evaluate_folders` (scores depth PNG / ``.npy`` files matched by frame, prediction
  holes counted), :class:`EvalResult`, :func:`format_eval_text` and :func:`write_eval_results`
  live in :mod:`sparsetools.train.results`, which needs no torch, and are re-exported here.

A model of input mode ``rgbdc`` is fed the split's confidence maps (the dataset refuses a split
without them before evaluating anything); a URL model (``rgbdu``) the ``D_c`` and ``U`` of the
densifier its checkpoint carries.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch

from ..ops.metrics import aggregate_metrics, depth_metrics
from .checkpoint import Checkpoint, load_checkpoint, model_from_checkpoint
from .data import DepthDataset, collate
from .densifier import open_densifier
from .losses import depth_loss
from .model import DepthCompletionUNet
from .results import (
    EvalResult,
    evaluate_folders,
    format_eval_text,
    pool_depth_bins,
    write_eval_results,
)
from .runtime import batches, make_loader, progress_bar, resolve_device, torch_settings

__all__ = [
    "EvalResult",
    "EvaluationPass",
    "batch_inputs",
    "cap_depth",
    "evaluate_checkpoint",
    "evaluate_folders",
    "evaluation_loader",
    "format_eval_text",
    "open_model",
    "picture_indices",
    "run_evaluation",
    "score_batch",
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


def evaluation_loader(dataset, *, batch_size: int, workers: int):
    """A loader over every sample of ``dataset`` in order (one by one when sizes differ)."""
    return make_loader(
        dataset,
        batch_size=eval_batch_size(dataset.output_sizes(), batch_size),
        order=None,
        workers=workers,
        seed=0,
        collate=collate,
    )


def rgb_uint8(rgb: torch.Tensor) -> np.ndarray:
    """(3, H, W) float 0..1 tensor -> (H, W, 3) uint8."""
    return np.clip(rgb.permute(1, 2, 0).numpy() * 255 + 0.5, 0, 255).astype(np.uint8)


def batch_inputs(batch: dict, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """What :meth:`DepthCompletionUNet.run` / ``depth_of`` take, from a :class:`DepthDataset`
    batch: ``rgb`` (B, 3, H, W), ``sparse`` (B, 1, H, W) metres, and the keyword arguments of
    the input mode (``confidence`` (B, 1, H, W) for ``rgbdc``; ``coarse`` and ``log_var``
    (B, 1, H, W) for ``rgbdu``; none otherwise), on ``device``.

    Use ``model.run(rgb, sparse, **extra)``.
    """
    rgb, sparse = batch["rgb"].to(device), batch["sparse"].to(device)
    extra = {k: batch[k].to(device) for k in ("confidence", "coarse", "log_var") if k in batch}
    return rgb, sparse, extra


def score_batch(
    depth: torch.Tensor,
    batch: dict,
    images: torch.Tensor,
    dataset,
    *,
    metric_kw: dict,
    pictures: tuple[int, ...] = (),
) -> tuple[list[dict], list[tuple]]:
    """Per-image metrics of a batch's predicted ``depth`` and the picture rows it gives.

    Parameters
    ----------
    depth : (B, 1, H, W) float, metres
        The predictions for ``batch`` (``gt``, ``sparse`` (B, 1, H, W), ``index`` (B,)).
    images : (B, 3, H, W) float, 0..1
        The camera images shown in the pictures.
    dataset
        Names the samples (``sample_id``).
    metric_kw : dict
        Keyword arguments of :func:`~sparsetools.ops.metrics.depth_metrics`.
    pictures : tuple of int
        Sample indices to draw (median-scaled like their metrics).

    Returns
    -------
    rows : list of dict
        ``{"id": ..., **metrics}`` per sample.
    pictures : list of tuple
        (rgb uint8, sparse, prediction, gt) of the samples in ``pictures``.
    """
    pred_np = depth[:, 0].float().cpu().numpy()
    gt_np = batch["gt"][:, 0].numpy()
    rows, pics = [], []
    for k, idx in enumerate(batch["index"].tolist()):
        m = depth_metrics(pred_np[k], gt_np[k], **metric_kw)
        rows.append({"id": dataset.sample_id(idx), **m})
        if idx in pictures:
            scale = m.get("scale", 1.0)
            shown = pred_np[k] * (scale if math.isfinite(scale) else 1.0)
            pics.append((rgb_uint8(images[k]), batch["sparse"][k, 0].numpy(), shown, gt_np[k]))
    return rows, pics


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
    loader = evaluation_loader(dataset, batch_size=batch_size, workers=workers)
    with progress_bar(len(loader), desc, progress) as bar:
        for batch in batches(loader):
            rgb, sparse, extra = batch_inputs(batch, device)
            gt = batch["gt"].to(device)
            pred = model.depth_of(rgb, sparse, **extra)
            n = len(rgb)
            if loss is not None:
                loss_sum += float(depth_loss(loss, pred, cap_depth(gt, max_depth))) * n
                n_loss += n
            rows, shown = score_batch(
                pred, batch, batch["rgb"], dataset, metric_kw=metric_kw, pictures=picture_indices
            )
            per_image += rows
            pics += shown
            bar.update(1)
    return EvaluationPass(per_image, (loss_sum / n_loss if n_loss else math.nan), pics)


def open_model(
    checkpoint: str | os.PathLike, *, device: str = "cpu", input_mode: str | None = None
) -> tuple[Checkpoint, DepthCompletionUNet, torch.device]:
    """A checkpoint's depth network, on ``device`` and in evaluation mode.

    Parameters
    ----------
    checkpoint : path-like
        ``best.pt`` / ``last.pt`` (or the run folder: its ``best.pt``); supervised or
        self-supervised.
    device : str
        ``cpu``, ``cuda``, ``cuda:N`` (checked).
    input_mode : str, optional
        Refuse a checkpoint of another input mode.

    Returns
    -------
    ckpt : Checkpoint
    model : DepthCompletionUNet
    device : torch.device
    """
    ckpt = load_checkpoint(checkpoint, input_mode=input_mode)
    dev = resolve_device(device)
    model = model_from_checkpoint(ckpt).to(dev)
    model.eval()
    return ckpt, model, dev


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
    bin_edges: tuple[float, ...] | None = None,
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
    bin_edges : (K + 1,) float, metres, optional
        Also the errors by ground-truth depth bin (``depth_bins`` of the result).

    Returns
    -------
    EvalResult
    """
    ckpt, model, dev = open_model(checkpoint, device=device, input_mode=input_mode)
    selfsup = ckpt.config.selfsup
    if median_scaling is None:
        median_scaling = selfsup is not None and not selfsup.metric_scale
    data = DepthDataset(
        dataset,
        split,
        augment=False,
        input_mode=ckpt.input_mode,
        densifier=open_densifier(ckpt.config, ckpt),
    )
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
                **({} if bin_edges is None else {"bin_edges": bin_edges}),
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
    depth_bins = pool_depth_bins(result.per_image, bin_edges)
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
        run_id=ckpt.run_id,
        depth_bins=depth_bins,
    )
