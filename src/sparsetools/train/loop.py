"""The supervised training loop of the early-fusion U-Net (depth completion).

A run writes its folder (:mod:`sparsetools.train.checkpoint` describes it) after every epoch:
``metrics.csv``, ``last.pt``, ``best.pt`` (lowest validation RMSE), ``curves.png`` and
prediction pictures.

The depth network may have a LiDAR branch (``lidar_encoder``: EffisDepth's SFE or its dense
twin, fused into the encoder; :mod:`sparsetools.train.model`), fed the batch's sparse depth.

Reproducibility: the model is initialised from ``torch.manual_seed(seed)``; the order of the
training samples of epoch ``e`` is a permutation drawn from ``(seed, e)`` and each sample's
augmentation from ``(seed, e, index)`` (:mod:`sparsetools.train.data`), so neither depends on
the number of DataLoader workers. ``torch.use_deterministic_algorithms`` is on while training
and the torch thread count is pinned (``threads``, default: the free cores, recorded in
``config.json``; :func:`sparsetools.train.runtime.default_threads`). On CPU two
runs with the same seed (and thread count) give identical metrics, and a run resumed from
``last.pt`` -- saved at the end of every epoch, or where ``max_steps`` stopped it, with the
model, optimizer, RNG states and the position inside the epoch -- continues exactly as if it
had never stopped.

Self-supervised training from video has its own loop (:func:`sparsetools.train.selfsup.loop.train_selfsup`);
:func:`train` dispatches to it when ``config.selfsup`` is set.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch

from ..errors import ParameterError, SparsetoolsError
from ..ops.metrics import METRIC_NAMES, aggregate_metrics
from .checkpoint import (
    TrainingState,
    check_run_dir,
    load_checkpoint,
    restore_optimizer,
)
from .config import TrainConfig, epoch_lr, resumed_config
from .data import DepthDataset, collate_samples
from .epochs import (
    TrainSummary,
    epoch_loader,
    make_optimizer,
    save_epoch_checkpoints,
    write_epoch_files,
)
from .evaluate import batch_inputs, cap_depth, picture_indices, run_evaluation
from .losses import depth_loss
from .model import STRIDE, DepthCompletionUNet
from .runtime import (
    background_saves,
    batches,
    default_threads,
    progress_bar,
    resolve_device,
    torch_settings,
    write_json,
)

__all__ = [
    "TrainSummary",
    "epoch_loader",
    "make_optimizer",
    "prepare_run",
    "train",
    "write_epoch_files",
]

log = logging.getLogger(__name__)


def _finished_with_these_settings(config: TrainConfig, out: Path) -> bool:
    """True when ``out`` holds a run that finished ``config.epochs`` epochs with every other
    setting equal to ``config``'s, and the dataset's manifest is older than its ``last.pt``."""
    last = out / "last.pt"
    manifest = Path(config.dataset) / "manifest.parquet"
    try:
        if not last.is_file() or manifest.stat().st_mtime > last.stat().st_mtime:
            return False
        ckpt = load_checkpoint(last)
        resumed_config(config, ckpt.config, None)  # raises on any other setting
    except (SparsetoolsError, OSError):
        return False  # the usual checks then say what is wrong
    saved = ckpt.config
    return (
        saved.epochs == config.epochs
        and saved.max_steps == config.max_steps
        and ckpt.state.epoch >= config.epochs
    )


def prepare_run(config: TrainConfig, *, resume: bool, explicit: set[str] | None):
    """Check the settings and the run folder; on ``resume`` load ``last.pt``.

    Returns
    -------
    config : TrainConfig
        The configuration to train with (the run's own when resuming).
    ckpt : Checkpoint or None
    """
    config.validate()
    out = Path(config.out_dir)
    if not resume and _finished_with_these_settings(config, out):
        # the resume rule of every batch command: a rerun of a finished run with the same
        # settings on an unchanged dataset is a no-op (make demo twice)
        log.warning("%s: finished run with these settings, up to date (nothing trained)", out)
        resume = True
    check_run_dir(out, Path(config.dataset), resume)
    ckpt = None
    if resume:
        ckpt = load_checkpoint(out / "last.pt")
        config = resumed_config(config, ckpt.config, explicit)
        config.validate()
    if config.threads is None:  # config.json records the count the results depend on
        saved = ckpt.config.threads if ckpt is not None else None
        config = replace(config, threads=saved or default_threads())
    return config, ckpt


def train(
    config: TrainConfig,
    *,
    resume: bool = False,
    progress: bool = False,
    explicit: set[str] | None = None,
    on_epoch: Callable[[dict], None] | None = None,
) -> TrainSummary:
    """Train the early-fusion U-Net on a sparsetools dataset.

    Parameters
    ----------
    config : TrainConfig
        With ``selfsup`` set, self-supervised training from video
        (:func:`sparsetools.train.selfsup.loop.train_selfsup`).
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
    TrainSummary

    Raises
    ------
    ParameterError, FormatError, OutputError
        Bad settings, a split without ground truth, an empty split, mixed image sizes without
        ``crop``, an existing run without ``resume``, a diverged loss.
    """
    config, ckpt = prepare_run(config, resume=resume, explicit=explicit)
    if config.self_supervised:
        from .selfsup.loop import train_selfsup

        return train_selfsup(config, ckpt=ckpt, progress=progress, on_epoch=on_epoch)
    out = Path(config.out_dir)
    device = resolve_device(config.device)

    train_set = DepthDataset(
        config.dataset,
        config.train_split,
        augment=True,
        crop=config.crop,
        seed=config.seed,
        scale_range=config.scale_range,
        jitter=config.jitter,
        input_mode=config.input_mode,
    )
    val_set = DepthDataset(
        config.dataset, config.val_split, augment=False, input_mode=config.input_mode
    )
    sizes = train_set.output_sizes()
    if len(sizes) > 1:
        listed = ", ".join(f"{h}x{w}" for h, w in sorted(sizes)[:4])
        raise ParameterError(
            f"split '{config.train_split}' mixes image sizes ({listed}, HxW): images of one "
            "batch must have one size; use --crop HxW",
            param="crop",
        )
    ((h, w),) = sizes
    tiny = math.ceil(h / STRIDE) * math.ceil(w / STRIDE) == 1
    if tiny and config.batch_size < 2:
        raise ParameterError(
            "images of at most 16x16 pixels need --batch-size >= 2 (batch norm)",
            param="batch_size",
        )

    started = time.perf_counter()
    with torch_settings(config.threads, device), background_saves():
        torch.manual_seed(config.seed)
        model = DepthCompletionUNet(
            config.input_mode,
            width=config.width,
            final_layer=config.final_layer,
            lidar_encoder=config.lidar_encoder,
        ).to(device)
        optimizer = make_optimizer(model.parameters(), config)
        state = TrainingState()
        if ckpt is not None:
            model.load_state_dict(ckpt.model)
            restore_optimizer(optimizer, ckpt)
            torch.set_rng_state(ckpt.rng["torch"])
            state = ckpt.state
        else:
            out.mkdir(parents=True, exist_ok=True)
        write_json(out / "config.json", config.to_dict())

        n_train = len(train_set)
        batches_per_epoch = math.ceil(n_train / config.batch_size)
        pics = picture_indices(len(val_set), config.pictures)
        metric_kw = {"max_depth": config.max_depth}

        while state.epoch < config.epochs and (
            config.max_steps is None or state.step < config.max_steps
        ):
            epoch = state.epoch
            loader = epoch_loader(train_set, config, state, tiny=tiny, collate=collate_samples)
            for group in optimizer.param_groups:
                group["lr"] = epoch_lr(config, epoch)
            model.train()
            t0 = time.perf_counter()
            with progress_bar(
                batches_per_epoch, f"epoch {epoch + 1}/{config.epochs}", progress
            ) as bar:
                bar.update(state.batch_in_epoch)
                for batch in batches(loader):
                    rgb, sparse, extra = batch_inputs(batch, device)
                    gt = cap_depth(batch["gt"].to(device), config.max_depth)
                    pred = model.run(rgb, sparse, **extra)
                    loss = depth_loss(config.loss, pred, gt)
                    if not torch.isfinite(loss):
                        raise ParameterError(
                            f"training diverged: {config.loss} loss is {float(loss.detach())} at "
                            f"step {state.step + 1}; lower --lr",
                            param="lr",
                        )
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    optimizer.step()
                    state.add_batch({"loss": float(loss.detach())}, len(rgb))
                    elapsed = state.epoch_seconds + time.perf_counter() - t0
                    bar.set_postfix(
                        loss=f"{state.epoch_mean('loss'):.4g}",
                        img_s=f"{state.epoch_samples / max(elapsed, 1e-9):.1f}",
                    )
                    bar.update(1)
            state.epoch_seconds += time.perf_counter() - t0
            complete = state.batch_in_epoch >= batches_per_epoch

            val = run_evaluation(
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
            means = aggregate_metrics(val.per_image)
            row = {
                "epoch": epoch + 1,
                "step": state.step,
                "batches": state.batch_in_epoch,
                "complete": int(complete),
                "train_loss": state.epoch_mean("loss"),
                "val_loss": val.loss,
                **{k: means[k] for k in METRIC_NAMES},
                "val_images": means["n_images"],
                "lr": optimizer.param_groups[0]["lr"],
                "seconds": round(state.epoch_seconds, 3),
                "samples_per_s": round(state.epoch_samples / max(state.epoch_seconds, 1e-9), 3),
            }
            # a partial epoch's row is replaced when the epoch is finished after --resume
            state.history = [r for r in state.history if r["epoch"] != row["epoch"]] + [row]
            improved = state.best.improves(means["rmse"])
            if improved:
                state.best.value, state.best.epoch, state.best.row = means["rmse"], epoch + 1, row
            if complete:
                state.start_epoch()
            kw = dict(config=config, model=model, optimizer=optimizer, state=state)
            save_epoch_checkpoints(out, improved=improved, **kw)
            write_epoch_files(
                out,
                state,
                loss_name=config.loss,
                metric="rmse",
                pictures=val.pictures,
                max_depth=config.max_depth,
            )
            log.info(
                "epoch %d: train loss %.4g, val RMSE %.4g m",
                row["epoch"],
                row["train_loss"],
                row["rmse"],
            )
            if on_epoch is not None:
                on_epoch(row)

    return TrainSummary(
        run_dir=str(out),
        input_mode=config.input_mode,
        self_supervised=False,
        epochs_done=state.epoch,
        steps=state.step,
        best_epoch=state.best.epoch,
        best_metric=state.best.name,
        best_value=state.best.value,
        last=state.history[-1] if state.history else None,
        seconds=round(time.perf_counter() - started, 2),
        threads=config.threads,
    )
