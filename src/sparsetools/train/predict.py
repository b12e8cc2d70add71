"""Depth maps of a trained checkpoint over one split of a dataset (``sparsetools predict``).

:func:`open_predictor` loads the checkpoint (:func:`~sparsetools.train.evaluate.open_model`,
the loading ``eval --checkpoint`` uses), opens the split and checks, before anything is
written, that the dataset provides what the checkpoint's input mode takes
(:func:`check_dataset_inputs`). It returns a :class:`Prediction`: a :class:`Predictor`, which
gives one sample's depth map at a time but runs the network on ``batch_size`` consecutive
samples of one image size at once, and the samples (manifest rows and the files each
prediction is made from) that the batch
job (:class:`~sparsetools.pipeline.predict.PredictJob`) turns into tasks (the command line
hands them over: pipeline/ and train/ do not import each other).

Predictions are the network's depth in metres, unscaled: a camera-only self-supervised model
is scale-ambiguous, so its maps are relative depth (``eval --scaling median`` scores them as
``eval --checkpoint`` does); every other model predicts metric depth.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import ParameterError
from .config import CONFIDENCE_MODES
from .data import DepthDataset, collate, open_split
from .densifier import open_densifier
from .evaluate import batch_inputs, open_model
from .runtime import torch_settings

__all__ = ["Prediction", "Predictor", "check_dataset_inputs", "open_predictor"]

#: What each input mode feeds the network besides the camera image (for messages).
_NEEDS = {"rgb": (), "d": ("sparse",), "rgbd": ("sparse",), "rgbdm": ("sparse",),
          "rgbdc": ("sparse", "confidence"), "rgbdu": ("sparse",)}  # fmt: skip
_NOUNS = {"sparse": "sparse depth", "confidence": "confidence map"}


def check_dataset_inputs(input_mode: str, reader, *, split: str, checkpoint) -> None:
    """Refuse a split that lacks what ``input_mode`` feeds the network (one line).

    Parameters
    ----------
    input_mode : str
        The checkpoint's (``rgb``, ``d``, ``rgbd``, ``rgbdm``, ``rgbdc``, ``rgbdu``).
    reader : DatasetReader
        The split (its manifest's ``sparse_path`` / ``sparse_parquet`` / ``confidence_path``).
    split : str
    checkpoint : path-like
        Named in the message.

    Raises
    ------
    ParameterError
        Some samples have no sparse depth (a mode other than ``rgb``) or no confidence map
        (``rgbdc``): the count, the first sample, and what the checkpoint takes.
    """
    m = reader.manifest
    ids = m.column("id").to_pylist()
    pngs, parts = m.column("sparse_path").to_pylist(), m.column("sparse_parquet").to_pylist()
    have = {
        "sparse": [a is not None or b is not None for a, b in zip(pngs, parts, strict=True)],
        "confidence": [p is not None for p in m.column("confidence_path").to_pylist()],
    }
    for need in _NEEDS.get(input_mode, ()):
        missing = [i for i, ok in zip(ids, have[need], strict=True) if not ok]
        if missing:
            raise ParameterError(
                f"{checkpoint} takes input '{input_mode}' (with a {_NOUNS[need]}), but "
                f"{len(missing)} of the {len(ids)} samples of split '{split}' of "
                f"{reader.root} have none (e.g. '{missing[0]}')",
                param="CHECKPOINT",
            )


def _sample_sources(reader, row) -> tuple[str, ...]:
    rels = [row.sparse_path, row.sparse_parquet, row.confidence_path]
    rgb = str(reader.rgb_path(row.id))  # in the dataset, or referenced
    return (rgb, *(str(reader.path(r)) for r in rels if r is not None))


class Predictor:
    """One sample's predicted depth at a time, the network run on batches of samples.

    Calls are expected in sample order (the batch job's serial order): a sample not yet
    predicted starts a batch of it and the following samples of the same image size (at most
    ``batch_size``); samples of an earlier batch not asked for are dropped.

    Parameters
    ----------
    model : DepthCompletionUNet
        In evaluation mode, on ``device``.
    dataset : DepthDataset
        The split, without augmentation.
    device : torch.device
    batch_size : int
    """

    def __init__(self, model, dataset: DepthDataset, *, device: torch.device, batch_size: int):
        self.model = model
        self.dataset = dataset
        self.device = device
        self.batch_size = int(batch_size)
        self.sizes = dataset.sizes()
        self._cache: dict[int, np.ndarray] = {}

    def _batch_of(self, index: int) -> list[int]:
        out = [index]
        size = self.sizes[index]
        while len(out) < self.batch_size and out[-1] + 1 < len(self.sizes):
            nxt = out[-1] + 1
            if self.sizes[nxt] != size:
                break
            out.append(nxt)
        return out

    @torch.no_grad()
    def depth(self, index: int) -> np.ndarray:
        """(H, W) float32 metres: the network's depth of sample ``index`` of the split."""
        index = int(index)
        if index not in self._cache:
            self._cache.clear()
            indices = self._batch_of(index)
            batch = collate([self.dataset[i] for i in indices])
            with torch_settings(None, self.device):
                rgb, sparse, extra = batch_inputs(batch, self.device)
                pred = self.model.depth_of(rgb, sparse, **extra)
            maps = pred[:, 0].float().cpu().numpy()
            self._cache = {i: maps[k] for k, i in enumerate(indices)}
        return self._cache.pop(index)


@dataclass(frozen=True)
class Prediction:
    """What :func:`open_predictor` opened.

    Attributes
    ----------
    predictor : Predictor
    rows : list of ManifestRow
        The split's samples, in order (``predictor.depth(i)`` is the map of ``rows[i]``).
    sources : list of tuple of str
        Per sample, the files its prediction is made from: the checkpoint, then the sample's
        image, sparse depth (PNG or Parquet part) and confidence map in the dataset.
    checkpoint : str
    kind : {'supervised', 'self-supervised'}
    input_mode : str
    relative_depth : bool
        A camera-only self-supervised model: its maps have no metric scale.
    """

    predictor: Predictor
    rows: list
    sources: list
    checkpoint: str
    kind: str
    input_mode: str
    relative_depth: bool


def open_predictor(
    checkpoint: str | os.PathLike,
    dataset: str | os.PathLike,
    *,
    split: str = "test",
    device: str = "cpu",
    batch_size: int = 4,
) -> Prediction:
    """Load a checkpoint and open a split for prediction, checked before anything is written.

    Parameters
    ----------
    checkpoint : path-like
        ``best.pt`` / ``last.pt`` of ``sparsetools train`` (or the run folder: its
        ``best.pt``), supervised or self-supervised.
    dataset : path-like
    split : str
        Its samples need no ground truth (a benchmark's test set has none).
    device : str
    batch_size : int

    Returns
    -------
    Prediction

    Raises
    ------
    ParameterError
        A missing or empty split, or one that lacks the checkpoint's inputs.
    FormatError
        A bad checkpoint (:func:`~sparsetools.train.checkpoint.load_checkpoint`).
    """
    ckpt, model, dev = open_model(checkpoint, device=device)
    reader = open_split(dataset, split, need_gt=False)
    check_dataset_inputs(ckpt.input_mode, reader, split=split, checkpoint=ckpt.path)
    data = DepthDataset(
        dataset, split, augment=False, need_gt=False,
        input_mode=ckpt.input_mode if ckpt.input_mode in CONFIDENCE_MODES else None,
        densifier=open_densifier(ckpt.config, ckpt),
    )  # fmt: skip
    ckpt_file = str(Path(ckpt.path).resolve())
    rows = [reader.row(i) for i in range(len(reader))]
    selfsup = ckpt.config.selfsup
    return Prediction(
        predictor=Predictor(model, data, device=dev, batch_size=batch_size),
        rows=rows,
        sources=[(ckpt_file, *_sample_sources(reader, r)) for r in rows],
        checkpoint=str(ckpt.path),
        kind=ckpt.kind,
        input_mode=ckpt.input_mode,
        relative_depth=bool(selfsup is not None and not selfsup.metric_scale),
    )
