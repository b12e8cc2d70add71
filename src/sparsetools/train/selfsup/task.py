"""Self-supervised training of depth and pose networks from frame triplets, as a
:class:`~sparsetools.train.epochs.TrainingTask`.

Same run folder, checkpoints, determinism and exact ``--resume`` as supervised training (the
epochs are :func:`sparsetools.train.epochs.fit`'s): one Adam (or SGD) optimizer over both
networks, the weights from ``torch.manual_seed(seed)`` (depth network first, then the pose
network; their LiDAR branches, ``--lidar-encoder`` and ``--pose-lidar-encoder``, from streams
of their own, so the image networks start alike whatever the branches;
:func:`sparsetools.train.model.build_lidar_encoder`; a pose branch also makes the triplets
carry all three frames' sparse depth), the sample order of epoch e from ``(seed, e)``, each
triplet's augmentation from ``(seed, e, index)``, and the auto-mask's tie-breaking noise of
step k from ``(seed, k)``; the SBM threshold is saved with the checkpoint. Validation after
every epoch reports the validation loss, the photometric error, the pose ATE when the
validation frames have true poses (per-snippet scaled, unscaled, and that of standing still:
:mod:`.pose_eval`) and, when every validation frame has ground truth, the depth metrics --
per-image median-scaled for camera-only models, unscaled with the sparse loss. ``best.pt`` is
the epoch with the lowest validation photometric error (``select_by='photometric'``, the
default: no ground truth is read to choose it), or the lowest validation RMSE
(``select_by='gt'``). A run whose last validation ATE is above ``pose_failure_ratio`` of the
standing-still ATE is flagged as a pose failure (a warning in the log, ``pose_failure`` in
the summary).

Metric runs (with the sparse loss) start every pixel at :data:`METRIC_INITIAL_DEPTH` and
scale the pose network's translation to match
(:func:`~sparsetools.train.selfsup.pose_net.metric_translation_scale`). LiDAR input options
against the shortcut of a LiDAR branch that learns to copy its input into the sparse loss:
``lidar_dropout`` (an empty input map on a fraction of training batches) and
``lidar_holdout`` (disjoint point sets for the input and the loss), both drawn from
``(seed, step)`` (:func:`split_lidar`); validation feeds every point.

With ``selfsup.pbr`` (RNW's priors-based regularization, :mod:`.pbr`), the depth network's
loss gains ``xi * L_G`` of a PatchGAN discriminator that is trained after every step on its own
optimizer (:meth:`SelfSupervisedTask.after_step`); its weights (from a stream of their own) and
optimizer are saved in the checkpoints, its losses logged as ``train_pbr_*``. Validation
losses leave the adversarial term out. Without ``pbr`` nothing of it runs.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch

from ...errors import ParameterError
from ...ops.metrics import METRIC_NAMES, aggregate_metrics
from ..checkpoint import Checkpoint, TrainingState, load_weights, restore_optimizer
from ..config import TrainConfig, epoch_lr
from ..epochs import StepResult, Validation, single_size
from ..evaluate import (
    EvaluationPass,
    cap_depth,
    evaluation_loader,
    picture_indices,
    score_batch,
)
from ..model import DepthCompletionUNet, disparity_to_depth
from ..runtime import batches, progress_bar
from .data import TripletDataset
from .losses import selfsup_loss
from .masks import StatisticsMask
from .pbr import PriorsRegularizer
from .pbr_reference import ReferenceDepths
from .pose_eval import evaluate_pose
from .pose_net import POSE_SCALE, PoseNet, metric_translation_scale, source_transforms

__all__ = [
    "METRIC_INITIAL_DEPTH",
    "SelfSupervisedTask",
    "noise_generator",
    "pose_translation_scale",
    "split_lidar",
    "validate_selfsup",
]


#: Initial depth of every pixel in runs with the sparse loss (metres).
METRIC_INITIAL_DEPTH = 10.0
#: ``noise_generator`` stream of validation (training steps are 0, 1, 2, ...).
VALIDATION_STREAM = 2**31


log = logging.getLogger(__name__)


def _generator(seed: int, stream: int, step: int) -> torch.Generator:
    state = np.random.SeedSequence([int(seed) % 2**32, stream, int(step)]).generate_state(1)[0]
    return torch.Generator().manual_seed(int(state))


def noise_generator(seed: int, step: int) -> torch.Generator:
    """The generator of the auto-mask noise of optimizer step ``step`` (CPU)."""
    return _generator(seed, 104729, step)


def pose_translation_scale(settings) -> float:
    """The pose network's translation scale of a run (:class:`SelfSupSettings`): the one set,
    else 0.01 for camera-only runs and :func:`metric_translation_scale` of
    :data:`METRIC_INITIAL_DEPTH` for runs with the sparse loss."""
    if settings.pose_translation_scale is not None:
        return float(settings.pose_translation_scale)
    if not settings.metric_scale:
        return POSE_SCALE
    return metric_translation_scale(METRIC_INITIAL_DEPTH, settings.depth_range)


def split_lidar(
    sparse: torch.Tensor, *, dropout: float, holdout: float, seed: int, step: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The LiDAR input and the sparse-loss target of training step ``step``.

    Parameters
    ----------
    sparse : (B, 1, H, W) float, metres, 0 = empty
    dropout : float
        Probability that the whole batch's input is an empty map.
    holdout : float
        Probability that a point goes to the loss only (else to the input only).
    seed, step : int
        Draws from their own stream (not the auto-mask's), the same on every device.

    Returns
    -------
    lidar_input, loss_target : (B, 1, H, W) float
        ``sparse`` for both when ``dropout = holdout = 0``. With ``holdout`` the two have no
        point in common and together hold every point of ``sparse``.
    """
    if dropout == 0 and holdout == 0:
        return sparse, sparse
    g = _generator(seed, 7793, step)
    dropped = float(torch.rand((), generator=g)) < dropout
    target = sparse
    lidar_input = sparse
    if holdout > 0:
        held = (torch.rand(sparse.shape, generator=g) < holdout).to(sparse.device)
        lidar_input = torch.where(held, torch.zeros_like(sparse), sparse)
        target = torch.where(held, sparse, torch.zeros_like(sparse))
    if dropped:
        lidar_input = torch.zeros_like(sparse)
    return lidar_input, target


def _split_has_gt(dataset: TripletDataset) -> bool:
    return all(dataset.reader.row(t.target)["gt_path"] is not None for t in dataset.triplets)


def _forward(depth_net, pose_net, batch, device, *, lidar_input=None):
    """Disparities, the two transforms, and the target frame's sparse depth
    (``lidar_input``: what the depth network gets instead of it)."""
    inputs = batch["inputs"].to(device)
    sparse = batch["sparse"].to(device)
    disparities = depth_net.run(inputs[:, 1], sparse if lidar_input is None else lidar_input)
    lidar = batch["sparse_frames"].to(device) if pose_net.uses_lidar else None
    transforms = source_transforms(pose_net, inputs[:, 0], inputs[:, 1], inputs[:, 2], lidar=lidar)
    return disparities, transforms, sparse


@torch.no_grad()
def validate_selfsup(
    depth_net: DepthCompletionUNet,
    pose_net: PoseNet,
    dataset: TripletDataset,
    config: TrainConfig,
    *,
    device: torch.device,
    sbm: StatisticsMask | None,
    with_metrics: bool,
    pictures: tuple[int, ...] = (),
    progress: bool = False,
) -> tuple[EvaluationPass, float]:
    """Validation loss, per-image metrics and pictures, and the mean photometric loss.

    The SBM threshold is used but not updated; the auto-mask noise comes from a fixed seed, so
    validation is the same function of the weights at every epoch.
    """
    settings = config.selfsup
    depth_net.eval()
    pose_net.eval()
    loader = evaluation_loader(dataset, batch_size=config.batch_size, workers=config.workers)
    generator = noise_generator(config.seed, VALIDATION_STREAM)
    metric_kw = {"max_depth": config.max_depth, "median_scaling": not settings.metric_scale}
    per_image, pics = [], []
    loss_sum, pe_sum, n = 0.0, 0.0, 0
    with progress_bar(len(loader), "validation", progress) as bar:
        for batch in batches(loader):
            disparities, transforms, sparse = _forward(depth_net, pose_net, batch, device)
            terms = selfsup_loss(
                disparities,
                batch["frames"].to(device),
                batch["K"].to(device),
                transforms,
                settings,
                sparse=cap_depth(sparse, config.max_depth),
                sbm=sbm,
                generator=generator,
            )
            b = len(batch["index"])
            loss_sum += float(terms.total) * b
            pe_sum += terms.photometric * b
            n += b
            if with_metrics:
                depth = disparity_to_depth(disparities[0], *settings.depth_range)
                rows, shown = score_batch(
                    depth,
                    batch,
                    batch["inputs"][:, 1],
                    dataset,
                    metric_kw=metric_kw,
                    pictures=pictures,
                )
                per_image += rows
                pics += shown
            bar.update(1)
    return EvaluationPass(per_image, loss_sum / max(n, 1), pics), pe_sum / max(n, 1)


def _check_scales(config: TrainConfig, train_set: TripletDataset) -> None:
    h, w = single_size(config, train_set)
    coarsest = 2 ** (config.selfsup.scales - 1)
    if math.ceil(min(h, w) / coarsest) < 2:
        raise ParameterError(
            f"{w}x{h} images are too small for {config.selfsup.scales} scales (the coarsest "
            "disparity needs 2x2 pixels): use larger images or fewer --scales",
            param="scales",
        )


class SelfSupervisedTask:
    """Depth and pose from frame triplets (:class:`~sparsetools.train.epochs.TrainingTask`).

    Parameters
    ----------
    config : TrainConfig
        Checked, with ``selfsup`` set.

    Raises
    ------
    ParameterError, FormatError
        A missing split, one without triplets or intrinsics, mixed image sizes, images too
        small for the scales (:class:`~sparsetools.train.selfsup.data.TripletDataset`).
    """

    self_supervised = True
    loss_name = "self-supervised"

    def __init__(self, config: TrainConfig):
        settings = config.selfsup
        self.config = config
        self.progress_terms = {"loss": "loss", "pe": "photometric"}
        common = dict(
            crop=config.crop,
            seed=config.seed,
            mcie=settings.mcie,
            mcie_clip=settings.mcie_clip,
            sparse_frames=settings.pose_lidar_encoder != "none",
        )
        self.train_set = TripletDataset(
            config.dataset, config.train_split, augment=True, jitter=config.jitter, **common
        )
        self.val_set = TripletDataset(
            config.dataset, config.val_split, augment=False, **{**common, "crop": None}
        )
        _check_scales(config, self.train_set)
        self.with_metrics = _split_has_gt(self.val_set)
        if settings.select_by == "gt" and not self.with_metrics:
            raise ParameterError(
                f"--select-by gt chooses best.pt by the validation RMSE, but not every frame "
                f"of split {config.val_split!r} has ground truth: use --select-by photometric",
                param="select_by",
            )
        self.best_metric = "rmse" if settings.select_by == "gt" else "photometric"
        count = config.pictures if self.with_metrics else 0
        self.pictures = picture_indices(len(self.val_set), count)
        self.sbm = (
            StatisticsMask(beta=settings.sbm_beta, q=settings.sbm_percentile)
            if settings.sbm
            else None
        )
        self.reference = None
        if settings.pbr is not None:  # checked now, before a run folder is made
            self.reference = ReferenceDepths(
                settings.pbr,
                split=config.train_split,
                size=single_size(config, self.train_set),
                max_depth=config.max_depth,
                seed=config.seed,
            )
            self.progress_terms["adv"] = "pbr_generator"
        self.device = torch.device("cpu")
        self.depth_net: DepthCompletionUNet | None = None
        self.pose_net: PoseNet | None = None
        self.pbr: PriorsRegularizer | None = None

    def build_networks(self, device: torch.device) -> list[torch.nn.Module]:
        config, settings = self.config, self.config.selfsup
        self.device = device
        self.depth_net = DepthCompletionUNet(
            config.input_mode,
            width=config.width,
            output="disparity",
            depth_range=settings.depth_range,
            # metric runs start at a metric depth (see sparsetools.train.model)
            initial_depth=METRIC_INITIAL_DEPTH if settings.metric_scale else None,
            lidar_encoder=config.lidar_encoder,
            lidar_scales=config.lidar_scales,
        ).to(device)
        self.pose_net = PoseNet(
            width=settings.pose_width,
            lidar_encoder=settings.pose_lidar_encoder,
            translation_scale=pose_translation_scale(settings),
        ).to(device)
        if self.reference is not None:  # not in the list: its optimizer is its own
            self.pbr = PriorsRegularizer(config, reference=self.reference, device=device)
        return [self.depth_net, self.pose_net]

    def restore(self, ckpt: Checkpoint) -> None:
        load_weights(self.depth_net, ckpt.model, ckpt.path, "depth-network")
        load_weights(self.pose_net, ckpt.pose_model, ckpt.path, "pose-network")
        if self.sbm is not None:
            self.sbm.threshold = ckpt.sbm_threshold
        if self.pbr is not None:
            load_weights(self.pbr.discriminator, ckpt.discriminator, ckpt.path, "discriminator")
            restore_optimizer(self.pbr.optimizer, ckpt, state=ckpt.discriminator_optimizer)

    def step(self, batch: dict, state: TrainingState) -> StepResult:
        config, settings = self.config, self.config.selfsup
        lidar_input, target = split_lidar(
            batch["sparse"].to(self.device),
            dropout=settings.lidar_dropout,
            holdout=settings.lidar_holdout,
            seed=config.seed,
            step=state.step,
        )
        disparities, transforms, _ = _forward(
            self.depth_net, self.pose_net, batch, self.device, lidar_input=lidar_input
        )
        terms = selfsup_loss(
            disparities,
            batch["frames"].to(self.device),
            batch["K"].to(self.device),
            transforms,
            settings,
            sparse=cap_depth(target, config.max_depth),
            sbm=self.sbm,
            update_sbm=True,
            generator=noise_generator(config.seed, state.step),
        )
        row = terms.as_row()
        if self.pbr is None:
            return StepResult(terms.total, row, len(batch["index"]))
        depth = disparity_to_depth(disparities[0], *settings.depth_range)
        adversarial = self.pbr.generator_loss(depth, step=state.step)
        total = terms.total + settings.pbr_weight * adversarial
        row.update(loss=float(total.detach()), pbr_generator=float(adversarial.detach()))
        return StepResult(total, row, len(batch["index"]))

    def after_step(self, state: TrainingState) -> dict[str, float]:
        """The discriminator's step after the networks' (PBR only): its loss terms."""
        if self.pbr is None:
            return {}
        return self.pbr.update_discriminator(lr=epoch_lr(self.config, state.epoch), step=state.step)

    def validate(self, state: TrainingState, *, progress: bool) -> Validation:
        config, sbm = self.config, self.sbm
        val, val_pe = validate_selfsup(
            self.depth_net,
            self.pose_net,
            self.val_set,
            config,
            device=self.device,
            sbm=sbm,
            with_metrics=self.with_metrics,
            pictures=self.pictures,
            progress=progress,
        )
        means = aggregate_metrics(val.per_image) if self.with_metrics else {}
        pose = evaluate_pose(
            self.pose_net,
            config.dataset,
            split=config.val_split,
            device=self.device,
            batch_size=config.batch_size,
        )
        columns = {
            "train_photometric": state.epoch_mean("photometric"),
            "train_reprojection": state.epoch_mean("reprojection"),
            "train_sparse": state.epoch_mean("sparse"),
            "train_mask_fraction": state.epoch_mean("mask_fraction"),
            **self._pbr_columns(state),
            "val_loss": val.loss,
            "photometric": val_pe,
            "median_scaling": int(not config.selfsup.metric_scale),
            **{k: means.get(k, math.nan) for k in METRIC_NAMES},
            "val_images": means.get("n_images", len(self.val_set)),
            "sbm_threshold": math.nan if sbm is None or sbm.threshold is None else sbm.threshold,
            "ate": math.nan if pose is None else pose.ate_mean,
            "ate_unscaled": math.nan if pose is None else pose.ate_unscaled_mean,
            "ate_still": math.nan if pose is None else pose.ate_still_mean,
        }
        return Validation(columns, val.pictures)

    def _pbr_columns(self, state: TrainingState) -> dict[str, float]:
        if self.pbr is None:  # the metrics rows of runs without PBR are as before it
            return {}
        names = ("pbr_generator", "pbr_discriminator", "pbr_real", "pbr_fake")
        return {f"train_{n}": state.epoch_mean(n) for n in names}

    def checkpoint_extras(self) -> dict:
        threshold = None if self.sbm is None else self.sbm.threshold
        extras = {"pose_model": self.pose_net, "sbm_threshold": threshold}
        if self.pbr is not None:
            extras["discriminator"] = self.pbr.discriminator
            extras["discriminator_optimizer"] = self.pbr.optimizer
        return extras

    def describe(self, row: dict) -> str:
        text = (
            f"train loss {row['train_loss']:.4g}, photometric {row['train_photometric']:.4g}, "
            f"val {self.best_metric} {row[self.best_metric]:.4g}"
        )
        if math.isfinite(row.get("ate", math.nan)):
            text += f", ATE {row['ate']:.3g} m (standing still {row['ate_still']:.3g} m)"
        if "train_pbr_discriminator" in row:
            text += (
                f", PBR L_G {row['train_pbr_generator']:.3g} "
                f"L_D {row['train_pbr_discriminator']:.3g}"
            )
        return text

    def finish(self, state: TrainingState) -> dict:
        extras: dict = {"selected_by": self.config.selfsup.select_by}
        row = state.history[-1] if state.history else {}
        ate, still = row.get("ate", math.nan), row.get("ate_still", math.nan)
        if math.isfinite(ate) and still > 0:
            ratio = ate / still
            limit = self.config.selfsup.pose_failure_ratio
            extras["pose_ate_ratio"] = round(ratio, 4)
            extras["pose_failure"] = bool(ratio > limit)
            if ratio > limit:
                log.warning(
                    "pose failure: the last validation ATE (%.3g m) is %.0f %% of that of "
                    "predicting no motion (%.3g m; limit %.0f %%): the pose network has not "
                    "learnt the motion, so the photometric loss taught the depth little "
                    "(docs/selfsup.md)",
                    ate,
                    100 * ratio,
                    still,
                    100 * limit,
                )
        return extras
