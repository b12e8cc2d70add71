"""The epoch skeleton every kind of training shares: :func:`fit` behind :class:`TrainingTask`.

A task (:class:`~sparsetools.train.supervised.SupervisedTask`,
:class:`~sparsetools.train.selfsup.task.SelfSupervisedTask`, or one of your own) holds what is
particular to one kind of training: its datasets, its networks, the loss of one batch and the
validation. :func:`fit` holds the rest, once: the run folder, its run id and ``config.json``, the weights
from ``torch.manual_seed(seed)``, the optimizer, ``--resume`` (weights, optimizer, RNG and the
position inside the epoch), the learning-rate schedule, the sample order and the loader, the
progress bar, the divergence check, and after every epoch the metrics row, ``best.pt`` /
``last.pt``, ``metrics.csv``, ``curves.png`` and the prediction pictures.

Reproducibility (:mod:`sparsetools.train.loop`) is the skeleton's: a task draws random numbers
only from generators seeded by the configuration (and the step), never from global state,
except in :meth:`TrainingTask.build_networks` (after ``torch.manual_seed(seed)``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import torch

from ..errors import ParameterError
from ..io.plots import require_matplotlib
from .checkpoint import (
    BestRecord,
    Checkpoint,
    TrainingState,
    new_run_id,
    restore_optimizer,
    save_checkpoint,
)
from .config import TrainConfig, epoch_lr
from .data import collate
from .model import STRIDE
from .plots import draw_curves, prediction_picture
from .runtime import (
    background_saves,
    batches,
    copy_file,
    epoch_order,
    make_loader,
    progress_bar,
    resolve_device,
    torch_settings,
    write_csv,
    write_json,
    write_png,
)

__all__ = [
    "StepResult",
    "TrainSummary",
    "TrainingTask",
    "Validation",
    "epoch_loader",
    "fit",
    "make_optimizer",
    "save_epoch_checkpoints",
    "single_size",
    "write_epoch_files",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StepResult:
    """What :meth:`TrainingTask.step` computed on one batch.

    ``loss`` is the scalar tensor to minimise; ``terms`` the per-batch means to log (``loss``,
    the total, among them: the epoch's ``train_loss`` is its per-sample mean); ``samples``
    the batch's size.
    """

    loss: torch.Tensor
    terms: dict[str, float]
    samples: int


@dataclass(frozen=True)
class Validation:
    """What :meth:`TrainingTask.validate` reports after an epoch.

    ``columns`` are the task's entries of the epoch's metrics row, in ``metrics.csv`` order
    (between ``train_loss`` and ``lr``), :attr:`TrainingTask.best_metric` among them;
    ``pictures`` the rows of :func:`~sparsetools.train.plots.prediction_picture`.
    """

    columns: dict[str, Any]
    pictures: list


@runtime_checkable
class TrainingTask(Protocol):
    """One kind of training, as :func:`fit` drives it.

    Attributes
    ----------
    train_set : torch Dataset
        The training samples: ``len``, ``set_epoch(epoch)`` (the augmentation stream) and
        items that :func:`~sparsetools.train.data.collate` stacks (tensors of one size).
    self_supervised : bool
        The kind of run (:class:`TrainSummary`, checkpoints).
    loss_name : str
        The loss, as ``curves.png`` and the divergence message name it (``"{loss_name} loss"``).
    best_metric : str
        The metrics-row column ``best.pt`` is chosen by (lower is better).
    progress_terms : dict of str to str
        Progress-bar label -> loss term shown (its epoch mean).

    Notes
    -----
    A task may also have ``after_step(state) -> dict``: called after every optimizer step
    (before the step is counted), for a network with an optimizer of its own (the PBR
    discriminator of :class:`~sparsetools.train.selfsup.task.SelfSupervisedTask`); the terms it
    returns join the step's. A task without it trains as before the hook existed.
    """

    train_set: Any
    self_supervised: bool
    loss_name: str
    best_metric: str
    progress_terms: dict[str, str]

    def build_networks(self, device: torch.device) -> Sequence[torch.nn.Module]:
        """The networks, on ``device``, built right after ``torch.manual_seed(seed)``; the
        first is the depth network (a checkpoint's ``model``); the optimizer takes their
        parameters in this order."""
        ...

    def restore(self, ckpt: Checkpoint) -> None:
        """Load the networks' weights and the task's own state from a checkpoint."""
        ...

    def step(self, batch: dict, state: TrainingState) -> StepResult:
        """Forward pass and loss of one training batch (``state.step``: steps done before)."""
        ...

    def validate(self, state: TrainingState, *, progress: bool) -> Validation:
        """Validation after an epoch (``state`` holds the epoch's training sums)."""
        ...

    def checkpoint_extras(self) -> dict:
        """Keyword arguments of :func:`~sparsetools.train.checkpoint.save_checkpoint` beyond
        the depth network, optimizer and state (the pose network, the SBM threshold)."""
        ...

    def describe(self, row: dict) -> str:
        """The log line of an epoch's metrics row."""
        ...

    def finish(self, state: TrainingState) -> dict:
        """After the last epoch: the task's entries of the summary (``selected_by``: what
        ``best.pt`` was chosen by; a self-supervised run's pose-failure flag), logging any
        warning about the run."""
        ...


@dataclass(frozen=True)
class TrainSummary:
    """What :func:`train` reports.

    ``best_metric`` names the validation metric ``best.pt`` was chosen by (lower is better)
    and ``best_value`` its value at ``best_epoch``; ``last`` is the last epoch's metrics row.
    """

    run_dir: str
    input_mode: str
    self_supervised: bool
    epochs_done: int
    steps: int
    best_epoch: int | None
    best_metric: str
    best_value: float
    last: dict | None
    seconds: float
    #: torch CPU threads the run used (CPU results are bit-identical for the same count)
    threads: int
    #: the run's id (config.json, every checkpoint, every metrics.csv row)
    run_id: str | None = None
    #: the task's entries (:meth:`TrainingTask.finish`)
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """Flat summary for the command line (``best_<metric>`` holds the best value)."""
        return {
            "run_dir": self.run_dir,
            "input_mode": self.input_mode,
            "mode": "self-supervised" if self.self_supervised else "supervised",
            "epochs_done": self.epochs_done,
            "steps": self.steps,
            "best_epoch": self.best_epoch,
            f"best_{self.best_metric}": self.best_value,
            "last": self.last,
            "threads": self.threads,
            "seconds": self.seconds,
            "run_id": self.run_id,
            **self.extras,
        }


def make_optimizer(params, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam, or SGD with momentum 0.9 and weight decay 1e-4, at ``config.lr``."""
    if config.optimizer == "adam":
        return torch.optim.Adam(params, lr=config.lr)
    return torch.optim.SGD(params, lr=config.lr, momentum=0.9, weight_decay=1e-4)


def epoch_loader(train_set, config: TrainConfig, state: TrainingState, *, tiny: bool):
    """The loader of the training samples still to do in epoch ``state.epoch``.

    The samples come in :func:`~sparsetools.train.runtime.epoch_order`, from the position
    ``state.batch_in_epoch`` (a resumed epoch), at most up to ``config.max_steps``; with
    ``tiny`` images (a 1x1 bottleneck) a trailing batch of one sample, which would break
    batch norm, is left out.
    """
    epoch = state.epoch
    train_set.set_epoch(epoch)
    todo = epoch_order(config.seed, epoch, len(train_set))[
        state.batch_in_epoch * config.batch_size :
    ]
    if config.max_steps is not None:
        todo = todo[: (config.max_steps - state.step) * config.batch_size]
    if tiny and len(todo) % config.batch_size == 1:
        todo = todo[:-1]
    return make_loader(
        train_set,
        batch_size=config.batch_size,
        order=todo,
        workers=config.workers,
        seed=config.seed + epoch,
        collate=collate,
    )


def write_epoch_files(
    out: Path,
    state: TrainingState,
    *,
    loss_name: str,
    metric: str,
    pictures: list,
    max_depth: float,
    run_id: str | None = None,
) -> None:
    """``metrics.csv``, ``curves.png`` and ``predictions/epoch_NNN.png`` after an epoch.

    Every ``metrics.csv`` row ends with the ``run_id`` column (the rows are the checkpoint's
    history: ``--resume`` refuses a folder whose metrics.csv names another run).
    """
    row = state.history[-1]
    columns = list(row)
    if run_id is not None:
        write_csv(
            out / "metrics.csv",
            [{**r, "run_id": run_id} for r in state.history],
            [*columns, "run_id"],
        )
    else:
        write_csv(out / "metrics.csv", state.history, columns)
    write_png(out / "curves.png", draw_curves(state.history, loss_name=loss_name, metric=metric))
    if pictures:
        write_png(
            out / "predictions" / f"epoch_{row['epoch']:03d}.png",
            prediction_picture(pictures, max_depth=max_depth),
        )


def save_epoch_checkpoints(out: Path, *, improved: bool, **kw) -> None:
    """``last.pt`` after an epoch, and ``best.pt`` when the epoch ``improved``.

    ``best.pt`` is written first and ``last.pt`` is then its copy: a crash between leaves
    ``last.pt`` older (its epoch is redone on ``--resume``), never a ``best.pt`` older than
    what ``last.pt`` records. ``kw`` goes to :func:`~sparsetools.train.checkpoint.save_checkpoint`.
    """
    if improved:
        save_checkpoint(out / "best.pt", **kw)
        copy_file(out / "best.pt", out / "last.pt")
    else:
        save_checkpoint(out / "last.pt", **kw)


def single_size(config: TrainConfig, train_set) -> tuple[int, int]:
    """The one (height, width) of the training samples.

    Raises
    ------
    ParameterError
        The split mixes image sizes (one batch needs one size: a crop is the way out).
    """
    sizes = train_set.output_sizes()
    if len(sizes) > 1:
        listed = ", ".join(f"{w}x{h}" for h, w in sorted(sizes)[:4])
        raise ParameterError(
            f"split '{config.train_split}' mixes image sizes ({listed}, WxH): images of one "
            "batch must have one size; use --crop-size WxH",
            param="--crop-size",
        )
    ((h, w),) = sizes
    return h, w


def _tiny(config: TrainConfig, train_set) -> bool:
    """Whether the images shrink to a 1x1 bottleneck (refused with a batch of one)."""
    h, w = single_size(config, train_set)
    tiny = math.ceil(h / STRIDE) * math.ceil(w / STRIDE) == 1
    if tiny and config.batch_size < 2:
        raise ParameterError(
            "images of at most 16x16 pixels need --batch-size >= 2 (batch norm)",
            param="batch_size",
        )
    return tiny


def _train_epoch(task, networks, optimizer, loader, config, state, *, progress: bool) -> None:
    """One pass over ``loader``: a step per batch, counted in ``state``."""
    epoch = state.epoch
    for group in optimizer.param_groups:
        group["lr"] = epoch_lr(config, epoch)
    for net in networks:
        net.train()
    batches_per_epoch = math.ceil(len(task.train_set) / config.batch_size)
    after_step = getattr(task, "after_step", None)
    t0 = time.perf_counter()
    with progress_bar(batches_per_epoch, f"epoch {epoch + 1}/{config.epochs}", progress) as bar:
        bar.update(state.batch_in_epoch)
        for batch in batches(loader):
            result = task.step(batch, state)
            if not torch.isfinite(result.loss):
                raise ParameterError(
                    f"training diverged: the {task.loss_name} loss is "
                    f"{float(result.loss.detach())} at step {state.step + 1}; lower --lr",
                    param="lr",
                )
            optimizer.zero_grad(set_to_none=True)
            result.loss.backward()
            optimizer.step()
            terms = result.terms if after_step is None else {**result.terms, **after_step(state)}
            state.add_batch(terms, result.samples)
            elapsed = state.epoch_seconds + time.perf_counter() - t0
            shown = {k: f"{state.epoch_mean(t):.4g}" for k, t in task.progress_terms.items()}
            bar.set_postfix(**shown, img_s=f"{state.epoch_samples / max(elapsed, 1e-9):.1f}")
            bar.update(1)
    state.epoch_seconds += time.perf_counter() - t0


def fit(
    task: TrainingTask,
    config: TrainConfig,
    *,
    ckpt: Checkpoint | None = None,
    progress: bool = False,
    on_epoch: Callable[[dict], None] | None = None,
) -> TrainSummary:
    """Train ``task`` for ``config.epochs`` epochs (or ``config.max_steps`` steps) in
    ``config.out_dir``.

    Parameters
    ----------
    task : TrainingTask
    config : TrainConfig
        Checked (:func:`sparsetools.train.loop.prepare_run`), with ``threads`` set.
    ckpt : Checkpoint, optional
        The run's ``last.pt`` to continue from (its folder is ``config.out_dir``), checked by
        :func:`~sparsetools.train.checkpoint.resume_run_id`: the run continues under its
        ``run_id`` (a new run, or a checkpoint without an id, gets a new one).
    progress : bool
        A progress bar per epoch and per validation on stderr.
    on_epoch : callable, optional
        Called after each epoch with its metrics row (the columns of ``metrics.csv``).

    Returns
    -------
    TrainSummary
        The best epoch and value, the last row, the steps done.

    Raises
    ------
    ParameterError
        Mixed image sizes, images too small for a batch of one, a diverged loss.
    """
    require_matplotlib("training (its curves.png)")  # before an epoch is spent, not after
    out = Path(config.out_dir)
    device = resolve_device(config.device)
    tiny = _tiny(config, task.train_set)
    batches_per_epoch = math.ceil(len(task.train_set) / config.batch_size)
    started = time.perf_counter()
    # drawn from the operating system, not from torch's or numpy's streams: no result changes
    run_id = (ckpt.run_id if ckpt is not None else None) or new_run_id()
    with torch_settings(config.threads, device), background_saves():
        torch.manual_seed(config.seed)
        networks = list(task.build_networks(device))
        optimizer = make_optimizer([p for net in networks for p in net.parameters()], config)
        state = TrainingState(best=BestRecord(name=task.best_metric))
        if ckpt is not None:
            task.restore(ckpt)
            restore_optimizer(optimizer, ckpt)
            torch.set_rng_state(ckpt.rng["torch"])
            state = ckpt.state
        else:
            out.mkdir(parents=True, exist_ok=True)
        write_json(out / "config.json", {"run_id": run_id, **config.to_dict()})

        while state.epoch < config.epochs and (
            config.max_steps is None or state.step < config.max_steps
        ):
            epoch = state.epoch
            loader = epoch_loader(task.train_set, config, state, tiny=tiny)
            _train_epoch(task, networks, optimizer, loader, config, state, progress=progress)
            complete = state.batch_in_epoch >= batches_per_epoch
            val = task.validate(state, progress=progress)
            row = {
                "epoch": epoch + 1,
                "step": state.step,
                "batches": state.batch_in_epoch,
                "complete": int(complete),
                "train_loss": state.epoch_mean("loss"),
                **val.columns,
                "lr": optimizer.param_groups[0]["lr"],
                "seconds": round(state.epoch_seconds, 3),
                "samples_per_s": round(state.epoch_samples / max(state.epoch_seconds, 1e-9), 3),
            }
            # a partial epoch's row is replaced when the epoch is finished after --resume
            state.history = [r for r in state.history if r["epoch"] != row["epoch"]] + [row]
            value = row[task.best_metric]
            improved = state.best.improves(value)
            if improved:
                state.best.value, state.best.epoch, state.best.row = value, epoch + 1, row
            if complete:
                state.start_epoch()
            save_epoch_checkpoints(
                out,
                improved=improved,
                config=config,
                model=networks[0],
                optimizer=optimizer,
                state=state,
                run_id=run_id,
                **task.checkpoint_extras(),
            )
            write_epoch_files(
                out,
                state,
                loss_name=task.loss_name,
                metric=task.best_metric,
                pictures=val.pictures,
                max_depth=config.max_depth,
                run_id=run_id,
            )
            log.info("epoch %d: %s", row["epoch"], task.describe(row))
            if on_epoch is not None:
                on_epoch(row)

    return TrainSummary(
        run_dir=str(out),
        input_mode=config.input_mode,
        self_supervised=task.self_supervised,
        epochs_done=state.epoch,
        steps=state.step,
        best_epoch=state.best.epoch,
        best_metric=state.best.name,
        best_value=state.best.value,
        last=state.history[-1] if state.history else None,
        seconds=round(time.perf_counter() - started, 2),
        threads=config.threads,
        run_id=run_id,
        extras=task.finish(state),
    )
