"""The self-supervised training loop: depth and pose networks from frame triplets.

Same run folder, checkpoints, determinism and exact ``--resume`` as supervised training
(:mod:`sparsetools.train.loop`): one Adam (or SGD) optimizer over both networks, the weights
from ``torch.manual_seed(seed)`` (depth network first, then the pose network; their LiDAR
branches, ``--lidar-encoder`` and ``--pose-lidar-encoder``, from streams of their own, so the
image networks start alike whatever the branches; :func:`sparsetools.train.model.build_lidar_encoder`;
a pose branch also makes the triplets carry all three frames' sparse depth), the sample order
of epoch e from ``(seed, e)``, each triplet's augmentation from ``(seed, e, index)``, and the
auto-mask's tie-breaking noise of step k from ``(seed, k)``; the SBM threshold is saved with
the checkpoint. Validation after every epoch reports the validation loss, the photometric
error and, when every validation frame has ground truth, the depth metrics -- per-image
median-scaled for camera-only models, unscaled with the sparse loss. ``best.pt`` is the epoch
with the lowest validation RMSE (with ground truth), else the lowest photometric error.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ...errors import ParameterError
from ...ops.metrics import METRIC_NAMES, aggregate_metrics, depth_metrics
from ..checkpoint import (
    BestRecord,
    Checkpoint,
    TrainingState,
    load_weights,
    restore_optimizer,
)
from ..config import TrainConfig, epoch_lr
from ..epochs import (
    TrainSummary,
    epoch_loader,
    make_optimizer,
    save_epoch_checkpoints,
    write_epoch_files,
)
from ..evaluate import EvaluationPass, cap_depth, picture_indices, rgb_uint8
from ..model import STRIDE, DepthCompletionUNet, disparity_to_depth
from ..runtime import (
    background_saves,
    batches,
    make_loader,
    progress_bar,
    resolve_device,
    torch_settings,
    write_json,
)
from .data import TripletDataset, collate_triplets
from .losses import selfsup_loss
from .masks import StatisticsMask
from .pose_net import PoseNet, source_transforms

__all__ = ["noise_generator", "train_selfsup", "validate_selfsup"]

log = logging.getLogger(__name__)


#: Initial depth of every pixel in runs with the sparse loss (metres).
METRIC_INITIAL_DEPTH = 10.0
#: ``noise_generator`` stream of validation (training steps are 0, 1, 2, ...).
VALIDATION_STREAM = 2**31


def noise_generator(seed: int, step: int) -> torch.Generator:
    """The generator of the auto-mask noise of optimizer step ``step`` (CPU)."""
    state = np.random.SeedSequence([int(seed) % 2**32, 104729, int(step)]).generate_state(1)[0]
    return torch.Generator().manual_seed(int(state))


def _split_has_gt(dataset: TripletDataset) -> bool:
    return all(dataset.reader.row(t.target)["gt_path"] is not None for t in dataset.triplets)


def _forward(depth_net, pose_net, batch, device):
    inputs = batch["inputs"].to(device)
    sparse = batch["sparse"].to(device)
    disparities = depth_net.run(inputs[:, 1], sparse)
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
    loader = make_loader(
        dataset,
        batch_size=config.batch_size if len(dataset.output_sizes()) == 1 else 1,
        order=None,
        workers=config.workers,
        seed=0,
        collate=collate_triplets,
    )
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
                pred_np = depth[:, 0].float().cpu().numpy()
                gt_np = batch["gt"][:, 0].numpy()
                for k, idx in enumerate(batch["index"].tolist()):
                    m = depth_metrics(pred_np[k], gt_np[k], **metric_kw)
                    per_image.append({"id": dataset.sample_id(idx), **m})
                    if idx in pictures:
                        scale = m.get("scale", 1.0)
                        shown = pred_np[k] * (scale if math.isfinite(scale) else 1.0)
                        rgb = rgb_uint8(batch["inputs"][k, 1])
                        pics.append((rgb, batch["sparse"][k, 0].numpy(), shown, gt_np[k]))
            bar.update(1)
    return EvaluationPass(per_image, loss_sum / max(n, 1), pics), pe_sum / max(n, 1)


def _check_sizes(config: TrainConfig, train_set: TripletDataset) -> tuple[int, int]:
    sizes = train_set.output_sizes()
    if len(sizes) > 1:
        listed = ", ".join(f"{h}x{w}" for h, w in sorted(sizes)[:4])
        raise ParameterError(
            f"split '{config.train_split}' mixes image sizes ({listed}, HxW): images of one "
            "batch must have one size; use --crop HxW",
            param="crop",
        )
    ((h, w),) = sizes
    coarsest = 2 ** (config.selfsup.scales - 1)
    if math.ceil(min(h, w) / coarsest) < 2:
        raise ParameterError(
            f"{h}x{w} images are too small for {config.selfsup.scales} scales (the coarsest "
            "disparity needs 2x2 pixels): use larger images or fewer --scales",
            param="scales",
        )
    return h, w


def train_selfsup(
    config: TrainConfig,
    *,
    ckpt: Checkpoint | None = None,
    progress: bool = False,
    on_epoch: Callable[[dict], None] | None = None,
) -> TrainSummary:
    """Self-supervised training (call through :func:`sparsetools.train.loop.train`).

    Parameters
    ----------
    config : TrainConfig
        Checked, with ``selfsup`` set (the run's own configuration when resuming).
    ckpt : Checkpoint, optional
        The run's ``last.pt`` to continue from.
    progress : bool
    on_epoch : callable, optional
        Called with each epoch's metrics row.
    """
    settings = config.selfsup
    out = Path(config.out_dir)
    device = resolve_device(config.device)
    common = dict(
        crop=config.crop,
        seed=config.seed,
        mcie=settings.mcie,
        mcie_clip=settings.mcie_clip,
        sparse_frames=settings.pose_lidar_encoder != "none",
    )
    train_set = TripletDataset(
        config.dataset, config.train_split, augment=True, jitter=config.jitter, **common
    )
    val_set = TripletDataset(
        config.dataset, config.val_split, augment=False, **{**common, "crop": None}
    )
    h, w = _check_sizes(config, train_set)
    tiny = math.ceil(h / STRIDE) * math.ceil(w / STRIDE) == 1
    if tiny and config.batch_size < 2:
        raise ParameterError(
            "images of at most 16x16 pixels need --batch-size >= 2 (batch norm)",
            param="batch_size",
        )
    with_metrics = _split_has_gt(val_set)
    best_name = "rmse" if with_metrics else "photometric"

    started = time.perf_counter()
    with torch_settings(config.threads, device), background_saves():
        torch.manual_seed(config.seed)
        depth_net = DepthCompletionUNet(
            config.input_mode,
            width=config.width,
            output="disparity",
            depth_range=settings.depth_range,
            # metric runs start at a metric depth (see sparsetools.train.model)
            initial_depth=METRIC_INITIAL_DEPTH if settings.metric_scale else None,
            lidar_encoder=config.lidar_encoder,
        ).to(device)
        pose_net = PoseNet(width=settings.pose_width, lidar_encoder=settings.pose_lidar_encoder).to(
            device
        )
        optimizer = make_optimizer([*depth_net.parameters(), *pose_net.parameters()], config)
        sbm = (
            StatisticsMask(beta=settings.sbm_beta, q=settings.sbm_percentile)
            if settings.sbm
            else None
        )
        state = TrainingState(best=BestRecord(name=best_name))
        if ckpt is not None:
            load_weights(depth_net, ckpt.model, ckpt.path, "depth-network")
            load_weights(pose_net, ckpt.pose_model, ckpt.path, "pose-network")
            restore_optimizer(optimizer, ckpt)
            torch.set_rng_state(ckpt.rng["torch"])
            state = ckpt.state
            if sbm is not None:
                sbm.threshold = ckpt.sbm_threshold
        else:
            out.mkdir(parents=True, exist_ok=True)
        write_json(out / "config.json", config.to_dict())

        n_train = len(train_set)
        batches_per_epoch = math.ceil(n_train / config.batch_size)
        pics = picture_indices(len(val_set), config.pictures if with_metrics else 0)

        while state.epoch < config.epochs and (
            config.max_steps is None or state.step < config.max_steps
        ):
            epoch = state.epoch
            loader = epoch_loader(train_set, config, state, tiny=tiny, collate=collate_triplets)
            for group in optimizer.param_groups:
                group["lr"] = epoch_lr(config, epoch)
            depth_net.train()
            pose_net.train()
            t0 = time.perf_counter()
            with progress_bar(
                batches_per_epoch, f"epoch {epoch + 1}/{config.epochs}", progress
            ) as bar:
                bar.update(state.batch_in_epoch)
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
                        update_sbm=True,
                        generator=noise_generator(config.seed, state.step),
                    )
                    if not torch.isfinite(terms.total):
                        raise ParameterError(
                            f"training diverged: the self-supervised loss is "
                            f"{float(terms.total.detach())} at step {state.step + 1}; lower --lr",
                            param="lr",
                        )
                    optimizer.zero_grad(set_to_none=True)
                    terms.total.backward()
                    optimizer.step()
                    state.add_batch(terms.as_row(), len(batch["index"]))
                    elapsed = state.epoch_seconds + time.perf_counter() - t0
                    bar.set_postfix(
                        loss=f"{state.epoch_mean('loss'):.4g}",
                        pe=f"{state.epoch_mean('photometric'):.4g}",
                        img_s=f"{state.epoch_samples / max(elapsed, 1e-9):.1f}",
                    )
                    bar.update(1)
            state.epoch_seconds += time.perf_counter() - t0
            complete = state.batch_in_epoch >= batches_per_epoch

            val, val_pe = validate_selfsup(
                depth_net,
                pose_net,
                val_set,
                config,
                device=device,
                sbm=sbm,
                with_metrics=with_metrics,
                pictures=pics,
                progress=progress,
            )
            means = aggregate_metrics(val.per_image) if with_metrics else {}
            row = {
                "epoch": epoch + 1,
                "step": state.step,
                "batches": state.batch_in_epoch,
                "complete": int(complete),
                "train_loss": state.epoch_mean("loss"),
                "train_photometric": state.epoch_mean("photometric"),
                "train_reprojection": state.epoch_mean("reprojection"),
                "train_sparse": state.epoch_mean("sparse"),
                "train_mask_fraction": state.epoch_mean("mask_fraction"),
                "val_loss": val.loss,
                "photometric": val_pe,
                "median_scaling": int(not settings.metric_scale),
                **{k: means.get(k, math.nan) for k in METRIC_NAMES},
                "val_images": means.get("n_images", len(val_set)),
                "sbm_threshold": math.nan
                if sbm is None or sbm.threshold is None
                else sbm.threshold,
                "lr": optimizer.param_groups[0]["lr"],
                "seconds": round(state.epoch_seconds, 3),
                "samples_per_s": round(state.epoch_samples / max(state.epoch_seconds, 1e-9), 3),
            }
            state.history = [r for r in state.history if r["epoch"] != row["epoch"]] + [row]
            value = row[best_name]
            improved = state.best.improves(value)
            if improved:
                state.best.value, state.best.epoch, state.best.row = value, epoch + 1, row
            if complete:
                state.start_epoch()
            kw = dict(
                config=config,
                model=depth_net,
                optimizer=optimizer,
                state=state,
                pose_model=pose_net,
                sbm_threshold=None if sbm is None else sbm.threshold,
            )
            save_epoch_checkpoints(out, improved=improved, **kw)
            write_epoch_files(
                out,
                state,
                loss_name="self-supervised",
                metric=best_name,
                pictures=val.pictures,
                max_depth=config.max_depth,
            )
            log.info(
                "epoch %d: train loss %.4g, photometric %.4g, val %s %.4g",
                row["epoch"],
                row["train_loss"],
                row["train_photometric"],
                best_name,
                value,
            )
            if on_epoch is not None:
                on_epoch(row)

    return TrainSummary(
        run_dir=str(out),
        input_mode=config.input_mode,
        self_supervised=True,
        epochs_done=state.epoch,
        steps=state.step,
        best_epoch=state.best.epoch,
        best_metric=state.best.name,
        best_value=state.best.value,
        last=state.history[-1] if state.history else None,
        seconds=round(time.perf_counter() - started, 2),
        threads=config.threads,
    )
