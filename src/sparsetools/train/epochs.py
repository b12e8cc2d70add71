"""What the supervised and the self-supervised training loops share: the summary a run
returns, the optimizer, the loader of an epoch's samples and the files written after an epoch."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from .checkpoint import TrainingState, save_checkpoint
from .config import TrainConfig
from .plots import draw_curves, prediction_picture
from .runtime import copy_file, epoch_order, make_loader, write_csv, write_png

__all__ = [
    "TrainSummary",
    "epoch_loader",
    "make_optimizer",
    "save_epoch_checkpoints",
    "write_epoch_files",
]


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
        }


def make_optimizer(params, config: TrainConfig) -> torch.optim.Optimizer:
    """Adam, or SGD with momentum 0.9 and weight decay 1e-4, at ``config.lr``."""
    if config.optimizer == "adam":
        return torch.optim.Adam(params, lr=config.lr)
    return torch.optim.SGD(params, lr=config.lr, momentum=0.9, weight_decay=1e-4)


def epoch_loader(train_set, config: TrainConfig, state: TrainingState, *, tiny: bool, collate):
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
) -> None:
    """``metrics.csv``, ``curves.png`` and ``predictions/epoch_NNN.png`` after an epoch."""
    row = state.history[-1]
    write_csv(out / "metrics.csv", state.history, list(row))
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
