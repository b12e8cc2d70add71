"""What ``dataset report`` shows, gathered from a dataset: thumbnails, depth samples, the
recorded generation parameters, and the per-image results of ``sparsetools eval``.

No HTML here (:mod:`.report` assembles the page) and no plotting (:mod:`.report_plots`).
"""

from __future__ import annotations

import base64
import json
import math
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import FormatError
from ...io.dataset import ManifestRow
from ...io.dataset_reader import DatasetReader
from ...io.depth_files import read_depth_file
from ...io.image import read_image

__all__ = [
    "EVAL_METRIC",
    "EvalResults",
    "Thumbnail",
    "colour_scale_max",
    "depth_samples",
    "find_eval_results",
    "generation_summary",
    "pick_thumbnails",
    "read_eval_results",
    "thumbnail",
]

#: Width of a thumbnail, pixels (narrower images are not enlarged).
THUMB_WIDTH = 320
#: At most this many frames per split are read for the depth histograms (evenly spaced).
MAX_DEPTH_FRAMES = 200
#: At most this many depth values per frame and per kind go into a histogram (evenly strided).
MAX_VALUES_PER_FRAME = 5000
#: The per-image metric that orders the evaluated frames (largest first: worst first); RMSE is
#: what the KITTI depth-completion benchmark ranks by.
EVAL_METRIC = "rmse"
#: Largest eval results file read (bytes).
MAX_EVAL_BYTES = 256 << 20


# -- frames shown ----------------------------------------------------------------------------------
def pick_thumbnails(rows: list[ManifestRow], n: int) -> list[tuple[str, list[ManifestRow]]]:
    """The frames of one split shown as thumbnails, in titled groups, each frame once.

    With more than ``3 n`` frames: the ``n`` of lowest density, the ``n`` of highest density
    (densest first) and ``n`` spread evenly over the rest in id order; otherwise every frame,
    lowest density first. Ties are broken by id, so the choice is reproducible.
    """
    if n <= 0 or not rows:
        return []
    by_density = sorted(rows, key=lambda r: (r.density, r.id))
    if len(rows) <= 3 * n:
        return [("every frame, lowest density first", by_density)]
    low, high = by_density[:n], by_density[-n:][::-1]
    taken = {r.id for r in (*low, *high)}
    rest = sorted((r for r in rows if r.id not in taken), key=lambda r: r.id)
    idx = np.linspace(0, len(rest) - 1, n).round().astype(int) if rest else []
    spread = [rest[i] for i in dict.fromkeys(int(i) for i in idx)]
    return [
        ("lowest density", low),
        ("highest density", high),
        ("spread over the split (by id)", spread),
    ]


@dataclass(frozen=True)
class Thumbnail:
    """One frame drawn small: sparse depth coloured over its image.

    Attributes
    ----------
    id : str
    jpeg : bytes
    width, height : int
        Pixels of the thumbnail.
    """

    id: str
    jpeg: bytes
    width: int
    height: int

    def data_uri(self) -> str:
        return "data:image/jpeg;base64," + base64.b64encode(self.jpeg).decode("ascii")


def thumbnail(reader: DatasetReader, row: ManifestRow, *, max_depth: float) -> Thumbnail:
    """The image of ``row`` shrunk to :data:`THUMB_WIDTH` pixels with its sparse depth over it.

    The points are placed at the thumbnail's resolution (the nearest one where several fall
    in one pixel) and drawn as 3x3 squares, so that they stay visible however much the image
    shrinks.
    """
    import cv2

    from ...ops.colormap import overlay_depth

    rgb = read_image(reader.rgb_path(row.id))  # in the dataset, or referenced in place
    u, v, d = reader.sparse_points(row.id)
    h, w = rgb.shape[:2]
    s = min(1.0, THUMB_WIDTH / w)
    tw, th = max(1, round(w * s)), max(1, round(h * s))
    small = cv2.resize(rgb, (tw, th), interpolation=cv2.INTER_AREA) if s < 1 else rgb
    depth = np.full((th, tw), np.inf, np.float32)
    if u.size:
        tu = np.clip(((u.astype(np.float64) + 0.5) * s).astype(np.intp), 0, tw - 1)
        tv = np.clip(((v.astype(np.float64) + 0.5) * s).astype(np.intp), 0, th - 1)
        np.minimum.at(depth, (tv, tu), d.astype(np.float32))
    depth[~np.isfinite(depth)] = 0
    picture = overlay_depth(np.ascontiguousarray(small), depth, max_depth=max_depth, dilate=1)
    ok, buf = cv2.imencode(".jpg", picture[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 RGB picture
        raise FormatError(f"{row.id}: cannot encode its thumbnail")
    return Thumbnail(row.id, buf.tobytes(), tw, th)


# -- depth histograms ------------------------------------------------------------------------------
def _strided(values: np.ndarray) -> np.ndarray:
    step = max(1, math.ceil(values.size / MAX_VALUES_PER_FRAME))
    return values[::step]


def depth_samples(
    reader: DatasetReader, rows: list[ManifestRow]
) -> tuple[np.ndarray, np.ndarray, int]:
    """Sparse and ground-truth depths (metres) of up to :data:`MAX_DEPTH_FRAMES` frames of
    ``rows``, evenly spaced in id order; each frame gives at most
    :data:`MAX_VALUES_PER_FRAME` values of each kind (evenly strided).

    Returns
    -------
    sparse, gt : (N,) float32, (M,) float32
    frames : int
        Frames read (a frame whose files cannot be read is left out: ``verify`` reports it).
    """
    ordered = sorted(rows, key=lambda r: r.id)
    if len(ordered) > MAX_DEPTH_FRAMES:
        idx = np.linspace(0, len(ordered) - 1, MAX_DEPTH_FRAMES).round().astype(int)
        ordered = [ordered[i] for i in idx]
    sparse, gt, frames = [], [], 0
    for r in ordered:
        try:
            _, _, d = reader.sparse_points(r.id)
            g = None
            if r.gt_path is not None:
                g = read_depth_file(reader.path(r.gt_path, what="gt_path"))
        except (FormatError, OSError):
            continue
        frames += 1
        sparse.append(_strided(np.asarray(d, np.float32)))
        if g is not None:
            gt.append(_strided(g[np.isfinite(g) & (g > 0)].astype(np.float32)))
    cat = lambda parts: np.concatenate(parts) if parts else np.zeros(0, np.float32)  # noqa: E731
    return cat(sparse), cat(gt), frames


def colour_scale_max(values: np.ndarray) -> float:
    """Top of the thumbnails' colour scale: the 99th percentile of the sparse depths, rounded
    up to 10 m (80 m, KITTI's usual range, without depths)."""
    v = values[np.isfinite(values) & (values > 0)]
    if not v.size:
        return 80.0
    return float(max(10.0, 10.0 * math.ceil(float(np.percentile(v, 99)) / 10.0)))


# -- what the dataset records about how it was made ------------------------------------------------
def _flatten(obj, prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    out[prefix[:-1] or "value"] = json.dumps(obj, sort_keys=True)
    return out


@dataclass(frozen=True)
class ParamSummary:
    """One generation parameter over a set of samples.

    Attributes
    ----------
    name : str
        Dotted path in the ``generation_params`` JSON (``params.route``, ``inputs.gt``).
    values : list of (value, count)
        Its distinct values (JSON text), most common first; at most five are kept.
    distinct : int
        How many distinct values it has.
    samples : int
        Samples that record it.
    """

    name: str
    values: list[tuple[str, int]]
    distinct: int
    samples: int


def generation_summary(rows: list[ManifestRow]) -> list[ParamSummary]:
    """The ``generation_params`` of ``rows``, one line per parameter (nested keys dotted)."""
    seen: dict[str, dict[str, int]] = defaultdict(lambda: defaultdict(int))
    for r in rows:
        if not r.generation_params:
            continue
        try:
            params = json.loads(r.generation_params)
        except json.JSONDecodeError:
            params = {"(unreadable JSON)": r.generation_params[:80]}
        for k, v in _flatten(params).items():
            seen[k][v] += 1
    out = []
    for name in sorted(seen):
        counts = sorted(seen[name].items(), key=lambda kv: (-kv[1], kv[0]))
        out.append(ParamSummary(name, counts[:5], len(counts), sum(seen[name].values())))
    return out


# -- eval results ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class EvalResults:
    """The per-image metrics of one ``sparsetools eval`` results file.

    Attributes
    ----------
    path : str
    checkpoint, split : str, optional
        What was evaluated (None for an evaluation of prediction folders).
    metrics : dict
        The averages (``metrics`` of the file).
    rows : list of dict
        One per image (``id`` and the metrics), worst first by :data:`EVAL_METRIC`
        (images without a value last).
    not_in_dataset : int
        Evaluated images that are not samples of the dataset.
    """

    path: str
    checkpoint: str | None
    split: str | None
    metrics: dict
    rows: list[dict]
    not_in_dataset: int


def _number(v) -> bool:
    return v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))


def read_eval_results(path: str | os.PathLike, ids: set[str]) -> EvalResults:
    """An eval results file (JSON written by ``sparsetools eval``), checked as untrusted input.

    Raises
    ------
    FormatError
        Not such a file, a row without an ``id`` or with a value that is not a number, or no
        evaluated image that is a sample of the dataset (``ids``).
    """
    from ...io.sidecar import read_json_document

    path = Path(path)
    try:
        doc = read_json_document(path, what="eval results", max_bytes=MAX_EVAL_BYTES)
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: no such eval results file") from exc
    per_image = doc.get("per_image") if isinstance(doc, dict) else None
    if not isinstance(per_image, list):
        raise FormatError(f"{path}: not the results of `sparsetools eval` (no per_image list)")
    rows = []
    for i, r in enumerate(per_image):
        if not isinstance(r, dict) or not isinstance(r.get("id"), str):
            raise FormatError(f"{path}: per_image[{i}] has no id")
        bad = [k for k, v in r.items() if k != "id" and not _number(v)]
        if bad:
            raise FormatError(f"{path}: per_image[{i}] ({r['id']}): {bad[0]} is not a number")
        rows.append(r)
    inside = sum(r["id"] in ids for r in rows)
    if rows and not inside:
        raise FormatError(
            f"{path}: none of its {len(rows)} evaluated image(s) is a sample of the dataset "
            f"(first: {rows[0]['id']})"
        )

    def worst_first(r):
        v = r.get(EVAL_METRIC)
        ok = v is not None and math.isfinite(v)
        return (0 if ok else 1, -v if ok else 0.0, r["id"])

    metrics = doc.get("metrics") if isinstance(doc.get("metrics"), dict) else {}
    text = lambda k: doc[k] if isinstance(doc.get(k), str) else None  # noqa: E731
    return EvalResults(
        path=str(path),
        checkpoint=text("checkpoint"),
        split=text("split"),
        metrics={k: v for k, v in metrics.items() if _number(v)},
        rows=sorted(rows, key=worst_first),
        not_in_dataset=len(rows) - inside,
    )


def find_eval_results(path: str | os.PathLike, ids: set[str]) -> list[Path]:
    """The eval results files of ``--eval``: the file itself, or the ``eval_*.json`` of a
    train run folder that evaluated samples of this dataset (``ids``).

    Raises
    ------
    FormatError
        A folder without such a file (naming the command that writes one).
    """
    path = Path(path)
    if not path.is_dir():
        return [path]
    found = []
    for p in sorted(path.glob("eval_*.json")):
        try:
            read_eval_results(p, ids)
        except FormatError:
            continue
        found.append(p)
    if not found:
        raise FormatError(
            f"{path}: no eval results of this dataset (eval_*.json); write them with "
            f"`sparsetools eval --checkpoint {path}/best.pt DATASET --split SPLIT`"
        )
    return found
