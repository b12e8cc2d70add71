"""Evaluation results without torch: :class:`EvalResult`, metrics of depth files, JSON/CSV.

``sparsetools eval --pred DIR --gt DIR`` runs on this module alone (numpy metrics of
:mod:`sparsetools.ops.metrics`), so it works where PyTorch is not installed (``pip install
sparsetools`` without the ``train`` extra); :mod:`sparsetools.train.evaluate` adds the
evaluation of checkpoints, which needs torch, and re-exports these names.

- :func:`evaluate_folders` scores depth PNG / ``.npy`` files matched by frame: flat folders,
  sequence trees ``OUT/<sequence>/<frame>.png`` (what every sparsetools command writes),
  folders written by sparsetools and KITTI depth-completion trees
  (:func:`sparsetools.io.sources.index_input`); prediction holes are counted and scored as
  ``fill`` says (:func:`score_prediction`), never silently clipped;
- :func:`format_eval_text` is the table ``eval`` prints;
- :func:`write_eval_results` writes a result as JSON and CSV (:func:`eval_result_paths` names
  the two files; :func:`checkpoint_eval_path` is where ``eval --checkpoint`` puts them by
  default, one name per dataset, split and checkpoint); :class:`EvalTarget` is what an
  evaluation scored, recorded with its files so that the results of another evaluation are
  never replaced without ``--overwrite``.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import FormatError, ParameterError
from ..ops.metrics import (
    METRIC_NAMES,
    aggregate_depth_bins,
    aggregate_metrics,
    depth_metrics,
    evaluated_mask,
    format_metrics_table,
)
from .output_files import progress_bar, write_csv, write_json

if TYPE_CHECKING:
    from .selfsup.pose_eval import PoseAccuracy

__all__ = [
    "FILLS",
    "EvalResult",
    "EvalTarget",
    "checkpoint_eval_path",
    "eval_result_paths",
    "evaluate_folders",
    "format_eval_text",
    "pool_depth_bins",
    "score_prediction",
    "write_eval_results",
]

#: How prediction holes are scored (:func:`score_prediction`): ``none`` leaves them out of the
#: metrics (counted), ``nearest`` gives each the value of the nearest pixel with a prediction,
#: ``min-depth`` scores them as ``min_depth`` (monodepth2's clipping of a 0 prediction).
FILLS = ("none", "nearest", "min-depth")
#: Names of unmatched frames shown in messages and results.
SHOWN_NAMES = 5


@dataclass(frozen=True)
class EvalResult:
    """An evaluation: averaged and per-image metrics, the protocol, and what was evaluated.

    ``median_scaling`` is True when each prediction was scaled by median(gt) / median(pred)
    before the metrics (camera-only self-supervised models); the per-image rows then hold the
    ``scale``. Fields of the other kind of evaluation (checkpoint vs folders) are None.

    Evaluating prediction files (``fill`` set), every per-image row and ``metrics`` also hold
    ``n_holes``: evaluated ground-truth pixels where the prediction had no value (0, negative,
    NaN, infinite), scored as ``fill`` says.
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
    #: ``eval --pred``: how prediction holes were scored (:data:`FILLS`); per-image rows and
    #: ``metrics`` then hold ``n_holes``
    fill: str | None = None
    #: ``eval --pred``: the first predictions without ground truth (not evaluated)
    unmatched_predictions_first: list[str] | None = None
    #: ``eval --checkpoint``: the run id of the checkpoint (None: sparsetools 0.2.0)
    run_id: str | None = None
    #: ``eval --plot``: errors by ground-truth depth bin over all images
    #: (:func:`~sparsetools.ops.metrics.aggregate_depth_bins`)
    depth_bins: dict | None = None

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


def score_prediction(
    pred: np.ndarray,
    gt: np.ndarray,
    *,
    fill: str = "none",
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    garg_crop: bool = False,
    median_scaling: bool = False,
    bin_edges: tuple[float, ...] | None = None,
) -> dict:
    """The metrics of one predicted depth map, its holes counted and scored as ``fill`` says.

    A hole is an evaluated ground-truth pixel where the prediction has no value: 0, negative,
    NaN or infinite (0 is "no prediction" in KITTI's depth PNGs). Without this, a hole would
    be clipped to ``min_depth`` in silence (140 holes among 89,699 pixels gave an iRMSE of
    24,153 1/km).

    Parameters
    ----------
    pred, gt : (H, W) float, metres
    fill : {'none', 'nearest', 'min-depth'}
        ``none``: holes are left out of the metrics (and counted); ``nearest``: each hole takes
        the value of the nearest pixel with a prediction (a map without any stays all holes,
        left out); ``min-depth``: holes are scored as ``min_depth``, the clipping of
        monodepth2's protocol.
    min_depth, max_depth, garg_crop, median_scaling, bin_edges
        As :func:`~sparsetools.ops.metrics.depth_metrics`; median scaling uses the pixels
        scored (with ``min-depth``, the holes as 0).

    Returns
    -------
    dict
        :func:`~sparsetools.ops.metrics.depth_metrics`'s values (``n_pixels``: pixels scored)
        and ``n_holes``.
    """
    if fill not in FILLS:
        raise ParameterError(f"unknown fill {fill!r}; choose one of {', '.join(FILLS)}")
    pred = np.asarray(pred)
    gt = np.asarray(gt)
    kw = dict(
        min_depth=min_depth, max_depth=max_depth, garg_crop=garg_crop, median_scaling=median_scaling
    )
    if bin_edges is not None:
        kw["bin_edges"] = bin_edges
    if pred.shape != gt.shape:  # depth_metrics' own message
        return depth_metrics(pred, gt, **kw)
    with np.errstate(invalid="ignore"):
        has_value = np.isfinite(pred) & (pred > 0)
    holes = evaluated_mask(gt, min_depth=min_depth, max_depth=max_depth, garg_crop=garg_crop)
    holes &= ~has_value
    n_holes = int(np.count_nonzero(holes))
    if n_holes == 0:
        return {**depth_metrics(pred, gt, **kw), "n_holes": 0}
    if fill == "nearest" and has_value.any():
        from scipy.ndimage import distance_transform_edt

        nearest = distance_transform_edt(~has_value, return_distances=False, return_indices=True)
        scored = depth_metrics(pred[tuple(nearest)], gt, **kw)
    elif fill == "min-depth":  # 0 is clipped to min_depth by depth_metrics
        scored = depth_metrics(np.where(has_value, pred, 0.0), gt, **kw)
    else:  # none (or nothing to take a nearest value from): the holes are not scored
        scored = depth_metrics(np.where(has_value, pred, 0.0), np.where(holes, 0.0, gt), **kw)
    return {**scored, "n_holes": n_holes}


def _names(keys, n: int = SHOWN_NAMES) -> list[str]:
    return [str(k) for k in list(keys)[:n]]


def _listed(names: list[str], total: int) -> str:
    more = f", ... {total - len(names)} more" if total > len(names) else ""
    return ", ".join(names) + more


def match_depth_files(pred_dir, gt_dir) -> tuple[list[tuple[str, Path, Path]], list[str]]:
    """Ground-truth and prediction files matched by frame (:mod:`sparsetools.io.sources`).

    Returns
    -------
    pairs : list of (id, ground-truth path, prediction path)
        In frame order; ``id`` is ``<sequence>/<frame>`` (``<frame>`` in a flat folder).
    unmatched : list of str
        Predictions without ground truth (not evaluated), in frame order.

    Raises
    ------
    FormatError
        A ground-truth frame without a prediction (the count and the first names of both
        sides), no depth files, two files that are one frame.
    """
    from ..io.sources import index_input, match_keys

    gts = index_input(gt_dir, "gt", option="--gt").files
    preds = index_input(pred_dir, "depth", option="--pred").files
    found = match_keys(gts, preds)
    used = set(found.values())
    unmatched = [k for k, p in preds.items() if p not in used]
    missing = [k for k in gts if k not in found]
    if missing:
        extra = (
            f"; {len(unmatched)} prediction(s) have no ground truth "
            f"({_listed(_names(unmatched), len(unmatched))})"
            if unmatched
            else ""
        )
        raise FormatError(
            f"{len(missing)} of {len(gts)} ground-truth frame(s) have no prediction in "
            f"{pred_dir} ({_listed(_names(missing), len(missing))}){extra}: frames are matched "
            "by sequence and frame name"
        )
    return [(str(k), gts[k], found[k]) for k in gts], [str(k) for k in unmatched]


def evaluate_folders(
    pred_dir: str | os.PathLike,
    gt_dir: str | os.PathLike,
    *,
    garg_crop: bool = False,
    min_depth: float = 1e-3,
    max_depth: float = 80.0,
    median_scaling: bool = False,
    fill: str = "none",
    progress: bool = False,
    bin_edges: tuple[float, ...] | None = None,
) -> EvalResult:
    """Metrics of any method's predictions: depth files matched by frame.

    Parameters
    ----------
    pred_dir, gt_dir : path-like
        KITTI uint16 depth PNGs (or ``.npy`` metres): flat folders, sequence trees
        ``DIR/<sequence>/<frame>.png``, folders written by sparsetools or KITTI
        depth-completion trees; frames are matched by (sequence, frame), and by frame name
        alone where it is unique (a flat folder against a tree). Every ground-truth frame
        needs a prediction; predictions without ground truth are not evaluated, and are
        counted and named in the result.
    median_scaling : bool
        Per-image median scaling (for scale-ambiguous monocular methods).
    fill : {'none', 'nearest', 'min-depth'}
        How prediction holes are scored (:func:`score_prediction`); their count is in the
        result (``n_holes``, per image and in total).
    bin_edges : (K + 1,) float, metres, optional
        Also the errors by ground-truth depth bin (``depth_bins`` of the result).

    Raises
    ------
    FormatError
        A missing prediction (the first names on both sides), unreadable files, a prediction
        of another size than its ground truth, or nothing but holes to evaluate.
    """
    from ..io.depth_files import read_depth_file

    if fill not in FILLS:
        raise ParameterError(f"unknown fill {fill!r}; choose one of {', '.join(FILLS)}")
    pairs, unmatched = match_depth_files(pred_dir, gt_dir)
    per_image = []
    with progress_bar(len(pairs), "eval", progress, unit="image") as bar:
        for frame_id, gt_path, pred_path in pairs:
            gt = read_depth_file(gt_path)
            pred = read_depth_file(pred_path)
            if pred.shape != gt.shape:
                raise FormatError(
                    f"'{frame_id}': prediction is {pred.shape[1]}x{pred.shape[0]}, ground truth "
                    f"{gt.shape[1]}x{gt.shape[0]}"
                )
            m = score_prediction(
                pred,
                gt,
                fill=fill,
                min_depth=min_depth,
                max_depth=max_depth,
                garg_crop=garg_crop,
                median_scaling=median_scaling,
                bin_edges=bin_edges,
            )
            per_image.append({"id": frame_id, **m})
            bar.update(1)
    n_holes = sum(r["n_holes"] for r in per_image)
    if n_holes and not any(r["n_pixels"] for r in per_image):
        raise FormatError(
            f"every evaluated ground-truth pixel of the {len(per_image)} image(s) is a hole of "
            f"the prediction (0, NaN or infinite; {n_holes} pixels): nothing to evaluate "
            f"with --fill {fill}"
        )
    depth_bins = pool_depth_bins(per_image, bin_edges)
    metrics = aggregate_metrics(per_image)
    metrics["n_holes"] = n_holes
    return EvalResult(
        metrics=metrics,
        per_image=per_image,
        garg_crop=garg_crop,
        min_depth=min_depth,
        max_depth=max_depth,
        median_scaling=median_scaling,
        pred_dir=str(pred_dir),
        gt_dir=str(gt_dir),
        unmatched_predictions=len(unmatched),
        unmatched_predictions_first=_names(unmatched),
        fill=fill,
        depth_bins=depth_bins,
    )


def pool_depth_bins(per_image: list[dict], bin_edges) -> dict | None:
    """Take each row's ``depth_bins`` out (the per-image rows stay as without them) and pool
    them over the images (:func:`~sparsetools.ops.metrics.aggregate_depth_bins`)."""
    if bin_edges is None:
        return None
    bins = [r.pop("depth_bins") for r in per_image]
    return aggregate_depth_bins([{"depth_bins": b} for b in bins], bin_edges)


def format_eval_text(result: EvalResult, *, title: str = "") -> str:
    """The metrics table of a result, with the scaling protocol and the pose accuracy."""
    lines = [format_metrics_table(result.metrics, title=title)]
    if result.fill is not None:
        lines.append(_holes_text(result))
    if result.unmatched_predictions:
        n = result.unmatched_predictions
        names = _listed(result.unmatched_predictions_first or [], n)
        lines.append(
            f"{'unmatched':<13} {n} prediction(s) without ground truth, not evaluated: {names}"
        )
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
            f"({p.n_snippets} snippets of {p.snippet_length} frames, per-snippet scaled; "
            f"standing still: {p.ate_still_mean:.4f} m)"
        )
        lines.append(
            f"{'unscaled':<13} {p.ate_unscaled_mean:>10.4f} m  +- {p.ate_unscaled_std:.4f} "
            "(as predicted: the metric scale of a model with the sparse loss)"
        )
    return "\n".join(lines)


_FILL_WORDS = {
    "none": "left out of the metrics",
    "nearest": "given the nearest predicted value",
    "min-depth": "scored as --min-depth",
}


def _holes_text(result: EvalResult) -> str:
    """The line saying how many evaluated pixels had no prediction and what was done."""
    holes = int(result.metrics.get("n_holes", 0))
    pixels = int(result.metrics.get("n_pixels", 0)) + (holes if result.fill == "none" else 0)
    share = f" ({100.0 * holes / pixels:.2f} %)" if pixels else ""
    return (
        f"{'n_holes':<13} {holes:>10d} of {pixels} ground-truth pixels{share} had no prediction "
        f"(0/NaN): {_FILL_WORDS[result.fill]} (--fill {result.fill})"
    )


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

    The two files are :func:`eval_result_paths` of ``path``. The CSV has a row per image and
    a ``mean`` row (its ``n_pixels`` and ``n_holes`` are totals). Returns the files written.
    """
    json_path, csv_path = eval_result_paths(path)
    write_json(json_path, result.to_dict())
    holes = ["n_holes"] if result.fill is not None else []
    extra = ["scale"] if result.median_scaling else []
    columns = ["id", *METRIC_NAMES, "n_pixels", *holes, *extra]
    mean_row = {
        "id": "mean",
        **{k: result.metrics[k] for k in METRIC_NAMES},
        "n_pixels": result.metrics["n_pixels"],
        **{k: result.metrics[k] for k in holes},  # the total
    }
    write_csv(csv_path, [*result.per_image, mean_row], columns)
    return [json_path, csv_path]


@dataclass(frozen=True)
class EvalTarget:
    """What an evaluation scored: recorded with its result files (as the settings of
    :class:`~sparsetools.pipeline.output_file.OutputFile`), so that results of another dataset,
    split, checkpoint or prediction folder are never replaced without ``--overwrite``. Paths
    are absolute; protocol options (``--min-depth``, ``--scaling``...) are not part of it: a
    new protocol on the same data replaces eval's own results."""

    checkpoint: str | None = field(default=None, metadata={"option": "--checkpoint"})
    dataset: str | None = field(default=None, metadata={"option": "DATASET"})
    split: str | None = field(default=None, metadata={"option": "--split"})
    pred: str | None = field(default=None, metadata={"option": "--pred"})
    gt: str | None = field(default=None, metadata={"option": "--gt"})


_UNSAFE = re.compile(r"[^A-Za-z0-9._+-]+")


def _name_part(text: str, fallback: str) -> str:
    """``text`` as part of a file name: runs of other characters than letters, digits and
    ``._+-`` become ``_``, at most 80 characters."""
    part = _UNSAFE.sub("_", str(text)).strip("._")[:80]
    return part or fallback


def checkpoint_eval_path(
    checkpoint: str | os.PathLike, dataset: str | os.PathLike, split: str
) -> Path:
    """Where ``eval --checkpoint`` writes its results by default: next to the checkpoint, as
    ``eval_<dataset folder name>_<split>.json`` (``..._<checkpoint name>.json`` for another
    checkpoint than ``best.pt``), so that each dataset, split and checkpoint has its own files.

    Two datasets of the same folder name give the same file name: the second evaluation is
    refused (:class:`EvalTarget` is recorded with the files) rather than replace the first.
    """
    ckpt = Path(checkpoint)
    name = _name_part(Path(os.path.abspath(dataset)).name, "dataset")
    stem = f"eval_{name}_{_name_part(split, 'split')}"
    if ckpt.stem != "best":
        stem += f"_{_name_part(ckpt.stem, 'checkpoint')}"
    return ckpt.parent / f"{stem}.json"
