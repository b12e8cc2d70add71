"""Run folders and checkpoints: what ``last.pt`` / ``best.pt`` hold, written and read back checked.

A run folder holds::

    RUN_DIR/
      config.json           the run id and the training configuration
      metrics.csv           one row per epoch: train loss, validation loss and metrics, run id
      last.pt, best.pt      checkpoints (best = best validation metric)
      curves.png            loss and validation metric per epoch
      predictions/epoch_NNN.png   a few validation samples

A checkpoint file is a plain dict of tensors, numbers and strings (``torch.load(path,
weights_only=True)`` reads it): format tag and version, kind (``supervised`` or
``self-supervised``), the configuration, the depth model's constructor arguments and weights,
for self-supervised runs the pose network and the SBM threshold (with PBR the discriminator,
its configuration and its optimizer), for URL runs the learned densifier, the optimizer state, the position in training
(:class:`TrainingState`) and the torch RNG state. :func:`load_checkpoint` checks it and returns
a typed :class:`Checkpoint`.

A checkpoint file is untrusted input. :func:`load_checkpoint` refuses, with one
:class:`FormatError` naming the file, anything but torch's zip format read with
``weights_only=True`` (no pickled object ever runs; a legacy pickle file is refused before
torch sees it, and torch's warnings about such files are not printed), a model configuration
of the wrong types or of an absurd size (width above :data:`~sparsetools.train.config.MAX_WIDTH`:
checked before any layer is allocated), weights whose names or shapes do not fit that
configuration (compared with the network built on torch's ``meta`` device, which allocates
nothing), a training configuration of the wrong types or that contradicts the model's, and a
training state, optimizer state or RNG state of the wrong structure.

Every run has a **run id** (:func:`new_run_id`, 32 hex digits drawn when the run starts; no
random stream of training is touched), written in ``config.json``, in every checkpoint and in
every row of ``metrics.csv``. ``--resume`` continues a checkpoint only in its own run's folder
(:func:`resume_run_id`): a ``last.pt`` of another run, or a folder whose ``config.json``,
``metrics.csv`` or ``best.pt`` belongs to another run than its ``last.pt``, is refused with one
line naming both. Checkpoints of sparsetools 0.2.0 have no run id and still resume.
"""

from __future__ import annotations

import csv
import json
import math
import os
import uuid
import warnings
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..errors import FormatError, OutputError, ParameterError
from .checkpoint_checks import (
    CHECKPOINT_FORMAT,
    RUN_ID,
    check_agreement,
    check_discriminator,
    check_extras,
    check_model_config,
    check_pose_config,
    check_weights,
    load_weights,
    read_checkpoint_file,
)
from .config import TrainConfig
from .model import INPUT_CHANNELS, DepthCompletionUNet, build_model
from .runtime import save_torch

__all__ = [
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "KINDS",
    "RUN_FILES",
    "BestRecord",
    "Checkpoint",
    "TrainingState",
    "check_run_dir",
    "load_checkpoint",
    "load_weights",
    "model_from_checkpoint",
    "new_run_id",
    "pose_from_checkpoint",
    "restore_optimizer",
    "resume_run_id",
    "save_checkpoint",
]

#: 2 added self-supervised checkpoints (``kind``, pose network); version 1 files still load.
CHECKPOINT_VERSION = 2
KINDS = ("supervised", "self-supervised")
#: Files whose presence marks a folder as a run folder.
RUN_FILES = ("last.pt", "best.pt", "metrics.csv")
#: The other files a run writes; in a folder without a run they are someone else's.
OTHER_RUN_FILES = ("config.json", "curves.png", "predictions")
#: What a run id looks like (:func:`new_run_id`).
#: Larger run files are not read for their run id (``config.json`` is about 2 KB, a
#: ``metrics.csv`` of 1,000 epochs about 400 KB).
_MAX_RECORD_BYTES = 64 << 20


def new_run_id() -> str:
    """A fresh run id: 32 hex digits (``uuid4``, from the operating system's random source, so
    no random stream of training is touched)."""
    return uuid.uuid4().hex


@dataclass
class BestRecord:
    """The best validation result so far: metric name, its value, the epoch and its row."""

    name: str = "rmse"
    value: float = math.inf
    epoch: int | None = None
    row: dict | None = None

    def improves(self, value: float) -> bool:
        """Whether ``value`` (lower is better) beats the record."""
        return bool(value < self.value)


@dataclass
class TrainingState:
    """Where a run stands: enough, with the weights and RNG, to continue it exactly.

    ``epoch`` counts finished epochs; ``batch_in_epoch`` the batches done in the current one;
    ``epoch_sums`` the per-sample sums of the loss terms over those batches (``loss`` is the
    total) and ``epoch_samples`` their count; ``history`` one metrics row per epoch.
    """

    epoch: int = 0
    batch_in_epoch: int = 0
    step: int = 0
    epoch_sums: dict[str, float] = field(default_factory=dict)
    epoch_samples: int = 0
    epoch_seconds: float = 0.0
    best: BestRecord = field(default_factory=BestRecord)
    history: list[dict] = field(default_factory=list)

    def start_epoch(self) -> None:
        """Reset the per-epoch counters after an epoch is finished."""
        self.epoch += 1
        self.batch_in_epoch = 0
        self.epoch_sums = {}
        self.epoch_samples = 0
        self.epoch_seconds = 0.0

    def add_batch(self, terms: dict[str, float], n: int) -> None:
        """Count one optimizer step over ``n`` samples with the given loss terms (batch means)."""
        self.step += 1
        self.batch_in_epoch += 1
        for k, v in terms.items():
            self.epoch_sums[k] = self.epoch_sums.get(k, 0.0) + float(v) * n
        self.epoch_samples += n

    def epoch_mean(self, name: str) -> float:
        """Per-sample mean of loss term ``name`` over the batches of the current epoch."""
        return self.epoch_sums.get(name, 0.0) / max(self.epoch_samples, 1)

    def to_dict(self) -> dict:
        return {
            "epoch": self.epoch,
            "batch_in_epoch": self.batch_in_epoch,
            "step": self.step,
            "epoch_loss_sum": self.epoch_sums.get("loss", 0.0),  # version 1 readers
            "epoch_sums": dict(self.epoch_sums),
            "epoch_samples": self.epoch_samples,
            "epoch_seconds": self.epoch_seconds,
            "best": {
                self.best.name: self.best.value,
                "epoch": self.best.epoch,
                "metrics": self.best.row,
            },
            "best_metric": {
                "name": self.best.name,
                "value": self.best.value,
                "epoch": self.best.epoch,
            },
            "history": list(self.history),
        }

    @classmethod
    def from_dict(cls, d: dict) -> TrainingState:
        """The state saved by :meth:`to_dict` (a checkpoint's top level).

        Raises
        ------
        KeyError, TypeError, ValueError
            A missing entry or one of the wrong structure.
        """
        if not isinstance(d.get("history"), list) or not all(
            isinstance(r, dict) for r in d["history"]
        ):
            raise TypeError("history must be a list of metrics rows")
        if not isinstance(d.get("best"), dict):
            raise TypeError("best must be a mapping")
        if d.get("epoch_sums") is not None and not isinstance(d["epoch_sums"], dict):
            raise TypeError("epoch_sums must be a mapping")
        for name in ("epoch", "batch_in_epoch", "step", "epoch_samples"):
            if isinstance(d.get(name), bool) or not isinstance(d.get(name), int) or d[name] < 0:
                raise ValueError(f"{name} must be a non-negative integer")
        sums = d.get("epoch_sums")
        if sums is None:
            sums = {"loss": float(d["epoch_loss_sum"])} if d.get("epoch_samples") else {}
        bm = d.get("best_metric") or {"name": "rmse", "value": d["best"]["rmse"], "epoch": None}
        best = BestRecord(
            name=str(bm["name"]),
            value=float(bm["value"]),
            epoch=d["best"].get("epoch"),
            row=d["best"].get("metrics"),
        )
        return cls(
            epoch=int(d["epoch"]),
            batch_in_epoch=int(d["batch_in_epoch"]),
            step=int(d["step"]),
            epoch_sums={k: float(v) for k, v in sums.items()},
            epoch_samples=int(d["epoch_samples"]),
            epoch_seconds=float(d.get("epoch_seconds", 0.0)),
            best=best,
            history=list(d["history"]),
        )


@dataclass(frozen=True)
class Checkpoint:
    """A checked checkpoint (:func:`load_checkpoint`).

    Attributes
    ----------
    path : Path
    kind : {'supervised', 'self-supervised'}
    config : TrainConfig
    model_config : dict
        Constructor arguments of the depth network (:meth:`DepthCompletionUNet.config`).
    model : dict of str to Tensor
        The depth network's state dict.
    optimizer : dict
        The optimizer's state dict.
    state : TrainingState
    rng : dict
        ``torch``: the torch RNG state at the time of saving.
    pose_config, pose_model : dict or None
        The pose network (self-supervised runs only).
    sbm_threshold : float or None
        The running SBM threshold (self-supervised runs with ``sbm``; None before its first
        batch).
    discriminator_config, discriminator, discriminator_optimizer : dict or None
        PBR's discriminator (self-supervised runs with ``pbr``): constructor arguments,
        weights and its optimizer's state.
    run_id : str or None
        The run the checkpoint belongs to (None: written by sparsetools 0.2.0, before run ids).
    densifier : dict or None
        The learned densifier of a URL run (``input_mode='rgbdu'``): ``model_config``,
        ``model`` and ``run_id`` (:func:`sparsetools.train.densifier.densifier_record`).
    """

    path: Path
    kind: str
    config: TrainConfig
    model_config: dict
    model: dict
    optimizer: dict
    state: TrainingState
    rng: dict
    pose_config: dict | None = None
    pose_model: dict | None = None
    sbm_threshold: float | None = None
    run_id: str | None = None
    discriminator_config: dict | None = None
    discriminator: dict | None = None
    discriminator_optimizer: dict | None = None
    densifier: dict | None = None

    @property
    def input_mode(self) -> str:
        return self.model_config["input_mode"]

    @property
    def lidar_encoder(self) -> str:
        """The depth network's LiDAR branch (``'none'`` in checkpoints from before it)."""
        return self.model_config.get("lidar_encoder", "none")


def _is_run_config(path: Path) -> bool:
    """Whether ``path`` is the ``config.json`` of a training run (one that stopped before its
    first checkpoint)."""
    try:
        TrainConfig.from_dict(json.loads(path.read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError, ValueError):  # ParameterError is a ValueError
        return False
    return True


def check_run_dir(out: Path, dataset: Path, resume: bool) -> None:
    """Refuse a run folder that is a file, inside the dataset, taken, or holding files a run
    would replace that no run wrote.

    Raises
    ------
    OutputError
        ``out`` is a file, inside ``dataset``, already holds a run and ``resume`` is off, or
        holds ``config.json`` (not a run's), ``curves.png`` or ``predictions`` without a run.
    ParameterError
        ``resume`` and there is no ``last.pt`` to continue from.
    """
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
    for name in OTHER_RUN_FILES:
        path = out / name
        if path.exists() or path.is_symlink():
            if name == "config.json" and path.is_file() and _is_run_config(path):
                continue  # a run that stopped in its first epoch: it starts again
            raise OutputError(
                f"{path} exists and was not written by a training run (a run would replace "
                "it): choose another folder"
            )


def _state_dict_cpu(module: torch.nn.Module) -> dict:
    return {k: v.detach().cpu() for k, v in module.state_dict().items()}


def save_checkpoint(
    path: Path,
    *,
    config: TrainConfig,
    model: DepthCompletionUNet,
    optimizer: torch.optim.Optimizer,
    state: TrainingState,
    pose_model: torch.nn.Module | None = None,
    sbm_threshold: float | None = None,
    run_id: str | None = None,
    discriminator: torch.nn.Module | None = None,
    discriminator_optimizer: torch.optim.Optimizer | None = None,
    densifier: dict | None = None,
) -> None:
    """Write a checkpoint atomically (the torch RNG state is taken now), with the ``run_id`` of
    its run (and PBR's discriminator and its optimizer, a URL run's densifier, when given)."""
    obj = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "kind": "self-supervised" if config.self_supervised else "supervised",
        "config": config.to_dict(),
        "model_config": model.config(),
        "model": _state_dict_cpu(model),
        "optimizer": optimizer.state_dict(),
        **state.to_dict(),
        "val_metrics": state.history[-1] if state.history else None,
        "rng": {"torch": torch.get_rng_state()},
    }
    if pose_model is not None:
        obj["pose_config"] = pose_model.config()
        obj["pose_model"] = _state_dict_cpu(pose_model)
    if sbm_threshold is not None:
        obj["sbm_threshold"] = float(sbm_threshold)
    if run_id is not None:
        obj["run_id"] = str(run_id)
    if discriminator is not None:
        obj["discriminator_config"] = discriminator.config()
        obj["discriminator"] = _state_dict_cpu(discriminator)
        obj["discriminator_optimizer"] = discriminator_optimizer.state_dict()
    if densifier is not None:
        obj["densifier"] = densifier
    save_torch(obj, path)


def load_checkpoint(path: str | os.PathLike, *, input_mode: str | None = None) -> Checkpoint:
    """Read and check a checkpoint written by training.

    Parameters
    ----------
    path : path-like
        ``last.pt`` or ``best.pt`` (a run folder is accepted and means its ``best.pt``).
    input_mode : str, optional
        The input mode the caller will feed; a checkpoint of another mode is refused.

    Returns
    -------
    Checkpoint

    Raises
    ------
    FormatError
        Missing, unreadable or foreign file (a legacy pickle one included); a model or
        training configuration of the wrong types, of an absurd size, or contradicting each
        other; weights that do not fit the stored configuration; a malformed training,
        optimizer or RNG state (module docstring).
    ParameterError
        ``input_mode`` differs from the checkpoint's.
    """
    from .selfsup.pose_net import build_pose_net

    path = Path(path)
    if path.is_dir():
        path = path / "best.pt"
    if not path.is_file():
        raise FormatError(f"{path}: no such checkpoint")
    raw = read_checkpoint_file(path)
    version = raw.get("version", 0)
    if isinstance(version, bool) or not isinstance(version, int):
        raise FormatError(f"{path}: checkpoint version must be an integer, got {version!r}")
    if version > CHECKPOINT_VERSION:
        raise FormatError(f"{path}: checkpoint version {version} is newer than this sparsetools")
    kind = raw.get("kind", "supervised")
    if kind not in KINDS:
        raise FormatError(f"{path}: unknown checkpoint kind {kind!r}")
    mc = check_model_config(raw.get("model_config", {}), path)
    if input_mode is not None and mc["input_mode"] != input_mode:
        raise ParameterError(
            f"{path} was trained with input mode '{mc['input_mode']}' "
            f"({INPUT_CHANNELS[mc['input_mode']]} channels), not '{input_mode}'",
            param="input_mode",
        )
    weights = raw.get("model") if isinstance(raw.get("model"), dict) else {}
    stem = weights.get("stem.0.weight")
    expected = INPUT_CHANNELS[mc["input_mode"]]
    if not isinstance(stem, torch.Tensor) or stem.ndim != 4 or stem.shape[1] != expected:
        got = int(stem.shape[1]) if isinstance(stem, torch.Tensor) and stem.ndim == 4 else None
        raise FormatError(
            f"{path}: weights for {got} input channels do not match the stored input mode "
            f"'{mc['input_mode']}'"
        )
    check_weights(raw["model"], lambda: build_model(mc), path, "depth-network")
    pc = None
    if kind == "self-supervised":
        if raw.get("pose_model") is None or not raw.get("pose_config"):
            raise FormatError(f"{path}: self-supervised checkpoint without its pose network")
        pc = check_pose_config(raw["pose_config"], path)
        check_weights(raw["pose_model"], lambda: build_pose_net(pc), path, "pose-network")
    dc = check_discriminator(raw, path) if kind == "self-supervised" else None
    if "config" not in raw:
        raise FormatError(f"{path}: incomplete checkpoint (no training configuration)")
    try:
        config = TrainConfig.from_dict(raw["config"])
    except ParameterError as exc:
        raise FormatError(f"{path}: bad training configuration ({exc})") from exc
    check_agreement(config, mc, pc, kind, path, discriminator=dc)
    densifier = None
    if mc.get("url") is not None:
        from .densifier import check_densifier_record

        densifier = check_densifier_record(raw.get("densifier"), path)
    try:
        state = TrainingState.from_dict(raw)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise FormatError(f"{path}: incomplete checkpoint ({type(exc).__name__}: {exc})") from exc
    check_extras(raw, path)
    run_id = raw.get("run_id")
    if run_id is not None and not (isinstance(run_id, str) and RUN_ID.fullmatch(run_id)):
        raise FormatError(f"{path}: run_id must be 32 hex digits, got {_shown(run_id)}")
    return Checkpoint(
        path=path,
        kind=kind,
        config=config,
        model_config=mc,
        model=raw["model"],
        optimizer=raw.get("optimizer") or {},
        state=state,
        rng=raw["rng"],
        pose_config=pc,
        pose_model=raw.get("pose_model"),
        sbm_threshold=raw.get("sbm_threshold"),
        run_id=run_id,
        discriminator_config=dc,
        discriminator=raw.get("discriminator") if dc is not None else None,
        discriminator_optimizer=raw.get("discriminator_optimizer") if dc is not None else None,
        densifier=densifier,
    )


def restore_optimizer(
    optimizer: torch.optim.Optimizer, ckpt: Checkpoint, *, state: dict | None = None
) -> None:
    """Load a checkpoint's optimizer state (``state``: another of its optimizers' state, PBR's
    discriminator's); a mismatch is a one-line :class:`FormatError`."""
    try:
        optimizer.load_state_dict(ckpt.optimizer if state is None else state)
    except (ValueError, KeyError, TypeError, RuntimeError) as exc:
        detail = " ".join(str(exc).split())[:200]
        raise FormatError(
            f"{ckpt.path}: the optimizer state does not fit the model ({detail})"
        ) from exc


def model_from_checkpoint(ckpt: Checkpoint) -> DepthCompletionUNet:
    """The depth network of a checkpoint, with its weights (on CPU, in training mode)."""
    model = build_model(ckpt.model_config)
    load_weights(model, ckpt.model, ckpt.path, "depth-network")
    return model


def pose_from_checkpoint(ckpt: Checkpoint):
    """The pose network of a self-supervised checkpoint, with its weights (on CPU)."""
    from .selfsup.pose_net import build_pose_net

    if ckpt.pose_config is None or ckpt.pose_model is None:
        raise FormatError(f"{ckpt.path}: no pose network (a {ckpt.kind} checkpoint)")
    net = build_pose_net(ckpt.pose_config)
    load_weights(net, ckpt.pose_model, ckpt.path, "pose-network")
    return net


def _shown(value) -> str:
    """A run id as messages show it (``none`` for runs of sparsetools 0.2.0)."""
    if value is None:
        return "none (sparsetools 0.2.0)"
    if isinstance(value, str) and RUN_ID.fullmatch(value):
        return value
    text = repr(value)  # anything else, quoted: one line, whatever it holds
    return text if len(text) <= 40 else text[:37] + "..."


def _small_file(path: Path) -> bool:
    try:
        return path.is_file() and path.stat().st_size <= _MAX_RECORD_BYTES
    except OSError:
        return False


def _config_run_id(path: Path) -> tuple[bool, object]:
    """(readable, run id) of a run's ``config.json``: not readable when missing, too large or
    not a JSON object (the run rewrites it); the id is None when the file names none."""
    if not _small_file(path):
        return False, None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return False, None
    if not isinstance(d, dict):
        return False, None
    return True, d.get("run_id")


def _metrics_run_ids(path: Path) -> set:
    """The run ids in the ``run_id`` column of ``metrics.csv`` (empty: no file, no such column
    -- sparsetools 0.2.0 -- or a file that is not CSV text; the run rewrites it)."""
    if not _small_file(path):
        return set()
    try:
        with open(path, encoding="utf-8", newline="") as f:
            reader = csv.DictReader(f)
            if "run_id" not in (reader.fieldnames or ()):
                return set()
            return {row.get("run_id") or None for row in reader}
    except (OSError, UnicodeDecodeError, csv.Error):
        return set()


def _checkpoint_run_id(path: Path) -> tuple[bool, object]:
    """(readable, run id) of another checkpoint of the folder (``best.pt``), its tensors
    mapped, not read."""
    try:
        if not path.is_file() or not zipfile.is_zipfile(path):
            return False, None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            raw = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except Exception:  # torch raises many types; an unreadable best.pt tells nothing
        return False, None
    if not isinstance(raw, dict) or raw.get("format") != CHECKPOINT_FORMAT:
        return False, None
    return True, raw.get("run_id")


def resume_run_id(out: Path, ckpt: Checkpoint) -> str:
    """The run id ``--resume`` continues in ``out`` with ``ckpt`` (its ``last.pt``), after
    checking that the folder's files belong to that run.

    - ``metrics.csv``: every run id of its ``run_id`` column must be the checkpoint's (its
      rows are the checkpoint's history);
    - ``config.json``: when readable, it must name the checkpoint's run (a ``config.json``
      that is not a JSON object is rewritten from the checkpoint, so it does not count);
    - ``best.pt``: when it names a run, the one continued.

    A checkpoint of sparsetools 0.2.0 (no run id) continues under the id its folder's
    ``config.json`` names (a run that adopted it and stopped before its first epoch ended),
    else under a new one.

    Raises
    ------
    OutputError
        One line naming the two runs and the files they come from.
    """
    out = Path(out)
    last = ckpt.path
    remedy = (
        "--resume continues a run in its own folder only (put the run's files back together, "
        "or start a new run in another folder)"
    )
    for rid in sorted(_metrics_run_ids(out / "metrics.csv"), key=str):
        if rid != ckpt.run_id:
            raise OutputError(
                f"{out / 'metrics.csv'} belongs to run {_shown(rid)}, {last} to run "
                f"{_shown(ckpt.run_id)}: {remedy}"
            )
    readable, config_id = _config_run_id(out / "config.json")
    if ckpt.run_id is not None:
        if readable and config_id != ckpt.run_id:
            raise OutputError(
                f"{last} belongs to run {_shown(ckpt.run_id)}, but {out / 'config.json'} to "
                f"run {_shown(config_id)}: {remedy}"
            )
        run_id = ckpt.run_id
    elif isinstance(config_id, str) and RUN_ID.fullmatch(config_id):
        run_id = config_id
    else:
        run_id = new_run_id()
    readable, best_id = _checkpoint_run_id(out / "best.pt")
    if readable and best_id is not None and best_id != run_id:
        raise OutputError(
            f"{out / 'best.pt'} belongs to run {_shown(best_id)}, {last} to run "
            f"{_shown(ckpt.run_id if ckpt.run_id is not None else run_id)}: {remedy}"
        )
    return run_id
