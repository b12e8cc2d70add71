"""Supervised training of the early-fusion U-Net (depth completion), as a :class:`TrainingTask`.

The loss ``config.loss`` on the valid ground truth (capped at ``max_depth``) of augmented
samples (:class:`~sparsetools.train.data.DepthDataset`); validation after every epoch gives the
validation loss and the depth metrics, and ``best.pt`` is the epoch with the lowest RMSE.

The depth network may have a LiDAR branch (``lidar_encoder``: EffisDepth's SFE or its dense
twin, fused into the encoder; :mod:`sparsetools.train.model`), fed the batch's sparse depth.
With ``input_mode='rgbdu'`` it is URL's refinement of the learned densifier's ``D_c`` and ``U``
(:mod:`sparsetools.train.url`): the densifier computes them as samples are loaded, and every
checkpoint carries it.
The epochs themselves are :func:`sparsetools.train.epochs.fit`'s.
"""

from __future__ import annotations

import torch

from ..ops.metrics import METRIC_NAMES, aggregate_metrics
from .checkpoint import Checkpoint, TrainingState, load_weights
from .config import TrainConfig
from .data import DepthDataset
from .densifier import densifier_record, open_densifier
from .epochs import StepResult, Validation
from .evaluate import batch_inputs, cap_depth, picture_indices, run_evaluation
from .losses import depth_loss
from .model import DepthCompletionUNet

__all__ = ["SupervisedTask"]


class SupervisedTask:
    """Depth completion on ground truth (:class:`~sparsetools.train.epochs.TrainingTask`).

    Parameters
    ----------
    config : TrainConfig
        Checked, without ``selfsup``.
    ckpt : Checkpoint, optional
        The checkpoint a resumed run continues (a URL run takes its densifier from it).

    Raises
    ------
    ParameterError, FormatError
        A missing or empty split, one without ground truth, a crop larger than the images
        (:class:`~sparsetools.train.data.DepthDataset`); a missing or foreign densifier
        checkpoint (URL).
    """

    self_supervised = False
    best_metric = "rmse"

    def __init__(self, config: TrainConfig, *, ckpt: Checkpoint | None = None):
        self.config = config
        self.progress_terms = {"loss": "loss"}
        self.loss_name = config.loss
        self.densifier = open_densifier(config, ckpt)
        self.train_set = DepthDataset(
            config.dataset,
            config.train_split,
            augment=True,
            crop=config.crop,
            seed=config.seed,
            scale_range=config.scale_range,
            jitter=config.jitter,
            input_mode=config.input_mode,
            densifier=self.densifier,
        )
        self.val_set = DepthDataset(
            config.dataset,
            config.val_split,
            augment=False,
            input_mode=config.input_mode,
            densifier=self.densifier,
        )
        self.pictures = picture_indices(len(self.val_set), config.pictures)
        self.device = torch.device("cpu")
        self.model: DepthCompletionUNet | None = None

    def build_networks(self, device: torch.device) -> list[torch.nn.Module]:
        config = self.config
        self.device = device
        self.model = DepthCompletionUNet(
            config.input_mode,
            width=config.width,
            final_layer=config.final_layer,
            lidar_encoder=config.lidar_encoder,
            lidar_scales=config.lidar_scales,
            url=config.url,
            gate_alpha=config.gate_alpha,
            gate_beta=config.gate_beta,
        ).to(device)
        return [self.model]

    def restore(self, ckpt: Checkpoint) -> None:
        load_weights(self.model, ckpt.model, ckpt.path, "depth-network")

    def step(self, batch: dict, state: TrainingState) -> StepResult:
        rgb, sparse, extra = batch_inputs(batch, self.device)
        gt = cap_depth(batch["gt"].to(self.device), self.config.max_depth)
        loss = depth_loss(self.config.loss, self.model.run(rgb, sparse, **extra), gt)
        return StepResult(loss, {"loss": float(loss.detach())}, len(rgb))

    def validate(self, state: TrainingState, *, progress: bool) -> Validation:
        config = self.config
        val = run_evaluation(
            self.model,
            self.val_set,
            device=self.device,
            batch_size=config.batch_size,
            workers=config.workers,
            loss=config.loss,
            metric_kw={"max_depth": config.max_depth},
            max_depth=config.max_depth,
            picture_indices=self.pictures,
            progress=progress,
            desc="validation",
        )
        means = aggregate_metrics(val.per_image)
        columns = {
            "val_loss": val.loss,
            **{k: means[k] for k in METRIC_NAMES},
            "val_images": means["n_images"],
        }
        return Validation(columns, val.pictures)

    def checkpoint_extras(self) -> dict:
        return {} if self.densifier is None else {"densifier": densifier_record(self.densifier)}

    def finish(self, state: TrainingState) -> dict:
        url = {} if self.config.url is None else {"url": self.config.url}
        return {"selected_by": "gt", **url}

    def describe(self, row: dict) -> str:
        return f"train loss {row['train_loss']:.4g}, val RMSE {row['rmse']:.4g} m"
