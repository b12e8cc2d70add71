"""Evaluation results without torch: :class:`EvalResult`, metrics of depth files, JSON/CSV.

``sparsetools eval --pred DIR --gt DIR`` runs on this module alone (numpy metrics of
:mod:`sparsetools.ops.metrics`), so it works where PyTorch is not installed (``pip install
sparsetools`` without the ``train`` extra); :mod:`sparsetools.train.evaluate` adds the
evaluation of checkpoints, which needs torch, and re-exports these names.

- :func:`evaluate_folders` scores depth PNG / ``.npy`` files matched by stem;
- :func:`format_eval_text` is the table ``eval`` prints;
- :func:`write_eval_results` writes a result as JSON and CSV (:func:`eval_result_paths` names
  the two files).
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FormatError
from ..ops.metrics import METRIC_NAMES, aggregate_metrics, depth_metrics, format_metrics_table
from .output_files import progress_bar, write_csv, write_json

if TYPE_CHECKING:
    from .selfsup.pose_eval import PoseAccuracy

__all__ = [
    "EvalResult",
    "eval_result_paths",
    "evaluate_folders",
    "format_eval_text",
    "write_eval_results",
]


@dataclass(frozen=True)
class EvalResult:
    """An evaluation: averaged and per-image metrics, the protocol, and what was evaluated.

    ``median_scaling`` is True when each prediction was scaled by median(gt) / median(pred)
    before the metrics (camera-only self-supervised models); the per-image rows then hold the
    ``scale``. Fields of the other kind of evaluation (checkpoint vs folders) are None.
    """

    metrics: dict
    per_image: list[dict]
    garg_crop: bool
    min_depth: float
    max_depth: float
    median_scaling: bool = False
    checkpoint: str | None = None
    kind: str | None = None
    input_mode: str | None = None
    lidar_encoder: str | None = None
    epoch: int | None = None
    dataset: str | None = None
    split: str | None = None
    pred_dir: str | None = None
    gt_dir: str | None = None
    unmatched_predictions: int | None = None
    pose: PoseAccuracy | None = None

    def to_dict(self) -> dict:
        """JSON-ready dict (fields that do not apply are left out)."""
        out = {}
        for k, v in asdict(self).items():
            if v is None and k not in ("epoch",):
                continue
            out[k] = v
        if self.checkpoint is None:
            out.pop("epoch", None)
        return out


_DEPTH_SUFFIXES = (".png", ".npy")


def _depth_files(folder: Path, what: str) -> dict[str, Path]:
    if not folder.is_dir():
        raise FormatError(f"{folder}: no such {what} folder")
    files: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.is_file() and p.suffix.lower() in _DEPTH_SUFFIXES and not p.name.startswith("."):
            if p.stem in files:
                raise FormatError(f"{folder}: two {what} files for '{p.stem}'")
            files[p.stem] = p
    if not files:
        raise FormatError(f"{folder}: no depth PNG or .npy files ({what})")
    return files


def evaluate_folders(
    pred_dir: str | os.PathLike,
    gt_dir: str | os.PathLike,
    *,
    garg_crop: bool = False,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    median_scaling: bool = False,
    progress: bool = False,
) -> EvalResult:
    """Metrics of any method's predictions: depth files matched by stem.

    Parameters
    ----------
    pred_dir, gt_dir : path-like
        Folders of KITTI uint16 depth PNGs (or ``.npy`` metres); files are matched by stem.
        Every ground-truth file needs a prediction; predictions without ground truth are
        ignored (and counted).
    median_scaling : bool
        Per-image median scaling (for scale-ambiguous monocular methods).

    Raises
    ------
    FormatError
        A missing prediction, unreadable files, or a prediction of another size than its
        ground truth.
    """
    from ..io.dataset import read_depth_file

    preds = _depth_files(Path(pred_dir), "prediction")
    gts = _depth_files(Path(gt_dir), "ground-truth")
    missing = sorted(set(gts) - set(preds))
    if missing:
        raise FormatError(
            f"{len(missing)} of {len(gts)} ground-truth file(s) have no prediction in "
            f"{pred_dir} (e.g. '{missing[0]}')"
        )
    per_image = []
    with progress_bar(len(gts), "eval", progress, unit="image") as bar:
        for stem, gt_path in gts.items():
            gt = read_depth_file(gt_path)
            pred = read_depth_file(preds[stem])
            if pred.shape != gt.shape:
                raise FormatError(
                    f"'{stem}': prediction is {pred.shape[1]}x{pred.shape[0]}, ground truth "
                    f"{gt.shape[1]}x{gt.shape[0]}"
                )
            m = depth_metrics(
                pred,
                gt,
                min_depth=min_depth,
                max_depth=max_depth,
                garg_crop=garg_crop,
                median_scaling=median_scaling,
            )
            per_image.append({"id": stem, **m})
            bar.update(1)
    return EvalResult(
        metrics=aggregate_metrics(per_image),
        per_image=per_image,
        garg_crop=garg_crop,
        min_depth=min_depth,
        max_depth=max_depth,
        median_scaling=median_scaling,
        pred_dir=str(pred_dir),
        gt_dir=str(gt_dir),
        unmatched_predictions=len(set(preds) - set(gts)),
    )


def format_eval_text(result: EvalResult, *, title: str = "") -> str:
    """The metrics table of a result, with the scaling protocol and the pose accuracy."""
    lines = [format_metrics_table(result.metrics, title=title)]
    if result.median_scaling:
        scales = [r["scale"] for r in result.per_image if math.isfinite(r.get("scale", math.nan))]
        med = float(np.median(scales)) if scales else math.nan
        lines.append(
            f"{'scaling':<13} per-image median (monodepth2 protocol; median scale {med:.4g})"
        )
    elif result.kind == "self-supervised":
        lines.append(f"{'scaling':<13} none (metric scale from the sparse loss)")
    if result.pose is not None:
        p = result.pose
        lines.append(
            f"{'pose ATE':<13} {p.ate_mean:>10.4f} m  +- {p.ate_std:.4f} "
            f"({p.n_snippets} snippets of {p.snippet_length} frames)"
        )
    return "\n".join(lines)


def eval_result_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """The JSON and CSV files :func:`write_eval_results` writes for ``path``.

    ``path`` ending in ``.json`` or ``.csv`` names that file and its sibling with the other
    suffix; any other path is used as the stem.
    """
    path = Path(path)
    stem = path.with_suffix("") if path.suffix.lower() in (".json", ".csv") else path
    return stem.with_suffix(".json"), stem.with_suffix(".csv")


def write_eval_results(result: EvalResult, path: str | os.PathLike) -> list[Path]:
    """Write an evaluation as JSON and CSV (per image plus a ``mean`` row), atomically.

    The two files are :func:`eval_result_paths` of ``path``. Returns the files written.
    """
    json_path, csv_path = eval_result_paths(path)
    write_json(json_path, result.to_dict())
    extra = ["scale"] if result.median_scaling else []
    columns = ["id", *METRIC_NAMES, "n_pixels", *extra]
    mean_row = {
        "id": "mean",
        **{k: result.metrics[k] for k in METRIC_NAMES},
        "n_pixels": result.metrics["n_pixels"],
    }
    write_csv(csv_path, [*result.per_image, mean_row], columns)
    return [json_path, csv_path]
