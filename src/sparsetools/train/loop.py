"""Training on a sparsetools dataset: :func:`train`, supervised or self-supervised.

A run writes its folder (:mod:`sparsetools.train.checkpoint` describes it) after every epoch:
``metrics.csv``, ``last.pt``, ``best.pt`` (best validation metric), ``curves.png`` and
prediction pictures. :func:`train` checks the settings and the run folder
(:func:`prepare_run`), then drives one :class:`~sparsetools.train.epochs.TrainingTask` through
:func:`~sparsetools.train.epochs.fit`: :class:`~sparsetools.train.supervised.SupervisedTask`
(the loss on ground truth), or with ``config.selfsup``
:class:`~sparsetools.train.selfsup.task.SelfSupervisedTask` (depth and pose from video).

Reproducibility: the model is initialised from ``torch.manual_seed(seed)``; the order of the
training samples of epoch ``e`` is a permutation drawn from ``(seed, e)`` and each sample's
augmentation from ``(seed, e, index)`` (:mod:`sparsetools.train.data`), so neither depends on
the number of DataLoader workers. ``torch.use_deterministic_algorithms`` is on while training
and the torch thread count is pinned (``threads``, default: the CPUs this process may use, a
fixed function of the machine, recorded in ``config.json``;
:func:`sparsetools.train.runtime.default_threads`). On CPU two
runs with the same seed (and thread count) give identical metrics, and a run resumed from
``last.pt`` -- saved at the end of every epoch, or where ``max_steps`` stopped it, with the
model, optimizer, RNG states and the position inside the epoch -- continues exactly as if it
had never stopped.

Every run has a run id (in ``config.json``, every checkpoint and every ``metrics.csv`` row);
``resume`` continues ``last.pt`` only in its own run's folder
(:func:`sparsetools.train.checkpoint.resume_run_id`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from ..errors import SparsetoolsError
from .checkpoint import check_run_dir, load_checkpoint, resume_run_id
from .config import TrainConfig, resumed_config
from .densifier import densifier_file
from .epochs import TrainSummary, fit
from .runtime import default_threads
from .supervised import SupervisedTask

__all__ = ["TrainSummary", "prepare_run", "train"]

log = logging.getLogger(__name__)


def _finished_with_these_settings(config: TrainConfig, out: Path) -> bool:
    """True when ``out`` holds a run that finished ``config.epochs`` epochs with every other
    setting equal to ``config``'s, and the dataset's manifest (and a URL run's densifier
    checkpoint) is older than its ``last.pt``."""
    last = out / "last.pt"
    inputs = [Path(config.dataset) / "manifest.parquet"]
    if config.densifier is not None:
        inputs.append(densifier_file(config.densifier))
    try:
        if not last.is_file() or any(p.stat().st_mtime > last.stat().st_mtime for p in inputs):
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
    """Check the settings and the run folder; on ``resume`` load ``last.pt`` and check that
    the folder's files belong to its run (:func:`~sparsetools.train.checkpoint.resume_run_id`).

    Returns
    -------
    config : TrainConfig
        The configuration to train with (the run's own when resuming).
    ckpt : Checkpoint or None
        Its ``run_id`` is the run it continues (a checkpoint of sparsetools 0.2.0, which has
        none, continues under the id its folder's ``config.json`` names, or a new one).
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
        ckpt = replace(ckpt, run_id=resume_run_id(out, ckpt))
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
    """Train the early-fusion U-Net (and, self-supervised, the pose network) on a dataset.

    Parameters
    ----------
    config : TrainConfig
        With ``selfsup`` set, self-supervised training from video
        (:class:`sparsetools.train.selfsup.task.SelfSupervisedTask`).
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
        from .selfsup.task import SelfSupervisedTask

        task = SelfSupervisedTask(config)
    else:
        task = SupervisedTask(config, ckpt=ckpt)
    return fit(task, config, ckpt=ckpt, progress=progress, on_epoch=on_epoch)
