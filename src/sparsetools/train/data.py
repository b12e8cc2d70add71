"""The torch Dataset over a sparsetools dataset (Parquet manifest + PNG files).

Samples come from :class:`sparsetools.io.dataset.DatasetReader`. Training samples get a joint
geometric augmentation of rgb, sparse depth and ground truth (random scale with depth divided
by the scale as Ma & Karaman do, bottom-centre crop, horizontal flip; nearest-neighbour
resampling for both depth maps, so no depth value is invented) and a colour jitter of rgb only.
The input mode ``rgbdc`` adds the confidence map stored by ``dataset build --confidence``
(``jbf-expand``'s ``<frame>_conf.png``): it goes through the same crop, flip and
nearest-neighbour resize as the sparse depth it describes, and is not divided by the scale.
The input mode ``rgbdu`` (URL) adds the learned densifier's ``D_c`` and ``U``, computed from the
sparse map after the augmentation (:class:`DepthDataset`'s ``densifier``).

Randomness: each sample's augmentation draws from a generator seeded with
``(seed, epoch, sample index)``, so a run is reproducible whatever the number of DataLoader
workers and an interrupted run resumes with the very same augmentations.
"""

from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import Dataset

from ..errors import FormatError, ParameterError
from .config import CONFIDENCE_MODES

__all__ = [
    "DepthDataset",
    "SampleDataset",
    "augment_sample",
    "bottom_centre_crop",
    "check_confidence",
    "check_crop",
    "collate",
    "colour_jitter",
    "open_split",
]


def open_split(path, split: str, *, need_gt: bool = True):
    """A :class:`~sparsetools.io.dataset.DatasetReader` over ``split``, checked for training.

    Raises
    ------
    ParameterError
        The split is missing or empty.
    FormatError
        ``need_gt`` and some samples of the split have no ground truth.
    """
    from ..io.dataset_reader import DatasetReader

    reader = DatasetReader(path)
    if split not in reader.splits:
        raise ParameterError(
            f"dataset {path} has no samples in split '{split}' "
            f"(splits: {', '.join(reader.splits) or 'none'})"
        )
    reader = reader.split(split)
    if len(reader) == 0:
        raise ParameterError(f"split '{split}' of {path} is empty")
    if need_gt:
        missing = [
            r["id"]
            for r in reader.manifest.select(["id", "gt_path"]).to_pylist()
            if r["gt_path"] is None
        ]
        if missing:
            raise FormatError(
                f"split '{split}' of {path}: {len(missing)} of {len(reader)} sample(s) have no "
                f"ground truth (e.g. '{missing[0]}'); build the dataset with --gt"
            )
    return reader


def check_confidence(reader, *, split: str, input_mode: str) -> None:
    """Refuse, before any training, a split with samples that lack a confidence map.

    Parameters
    ----------
    reader : DatasetReader
        The split (:func:`open_split`); only its manifest's ``confidence_path`` is read.
    split : str
    input_mode : str
        The input that needs the maps (named in the message).

    Raises
    ------
    ParameterError
        Some or all samples have no ``confidence_path``.
    """
    ids = reader.manifest.column("id").to_pylist()
    paths = reader.manifest.column("confidence_path").to_pylist()
    missing = [i for i, p in zip(ids, paths, strict=True) if p is None]
    if missing:
        where = f"split '{split}' of {reader.root}"
        if len(missing) == len(ids):
            found = f"no sample of {where} has one"
        else:
            found = (
                f"{len(missing)} of the {len(ids)} samples of {where} have none "
                f"(e.g. '{missing[0]}')"
            )
        raise ParameterError(
            f"--input {input_mode} needs a confidence map for every sample, but {found}: "
            "build the dataset with --confidence (jbf-expand's <frame>_conf.png) or with "
            "`dataset nuscenes --jbf`",
            param="--input",
        )


def check_crop(crop: tuple[int, int] | None, sizes, split: str) -> None:
    """Refuse a crop ``(height, width)`` that is not positive or is larger than some of the
    images' ``sizes`` ((height, width) pairs) of ``split``; None passes.

    Raises
    ------
    ParameterError
        Naming ``--crop-size`` and the sizes as ``WxH``.
    """
    if crop is None:
        return
    ch, cw = crop
    if ch <= 0 or cw <= 0:
        raise ParameterError(f"crop must be positive, got {cw}x{ch} (WxH)", param="--crop-size")
    small = [(h, w) for h, w in sizes if h < ch or w < cw]
    if small:
        h, w = small[0]
        raise ParameterError(
            f"crop {cw}x{ch} (WxH) is larger than {len(small)} image(s) of split '{split}' "
            f"(e.g. {w}x{h})",
            param="--crop-size",
        )


def bottom_centre_crop(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """The bottom ``height`` rows and the central ``width`` columns of an (H, W, ...) array.

    The bottom is kept because that is where LiDAR and ground truth have data (KITTI's sky
    rows have none); an odd margin puts the extra column on the right.
    """
    h, w = array.shape[:2]
    if height > h or width > w:
        raise ParameterError(
            f"crop {width}x{height} (WxH) is larger than the {w}x{h} image", param="--crop-size"
        )
    left = (w - width) // 2
    return array[h - height :, left : left + width]


def _resize_nearest(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    import cv2

    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)


_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def colour_jitter(rgb: np.ndarray, factors) -> np.ndarray:
    """Brightness, contrast and saturation changes of an image.

    Parameters
    ----------
    rgb : (H, W, 3) float32, 0..1
    factors : (brightness, contrast, saturation)
        Multipliers (1 = unchanged); contrast scales about the mean grey level of ``rgb``.

    Returns
    -------
    (H, W, 3) float32, clipped to 0..1.
    """
    brightness, contrast, saturation = (np.float32(f) for f in factors)
    rgb = rgb * brightness
    grey = rgb @ _LUMA
    rgb = (rgb - grey.mean()) * contrast + grey.mean()
    grey = (rgb @ _LUMA)[:, :, None]
    return np.clip((rgb - grey) * saturation + grey, 0.0, 1.0)


def augment_sample(
    rgb: np.ndarray,
    sparse: np.ndarray,
    gt: np.ndarray,
    rng: np.random.Generator,
    *,
    crop: tuple[int, int] | None = None,
    scale_range: tuple[float, float] = (1.0, 1.0),
    flip: bool = True,
    jitter: float = 0.2,
    confidence: np.ndarray | None = None,
) -> tuple[np.ndarray, ...]:
    """Joint augmentation of one sample.

    Parameters
    ----------
    rgb : (H, W, 3) uint8
    sparse, gt : (H, W) float32, metres, 0 = empty
    rng : numpy.random.Generator
    crop : (height, width) or None
        Bottom-centre crop after scaling.
    scale_range : (low, high)
        Uniform scale factor s: images are resized by s (rgb bilinear, depth nearest) and
        depths divided by s (the scene seen s times closer). (1, 1) disables it.
    flip : bool
        Horizontal flip with probability 1/2.
    jitter : float
        Brightness, contrast and saturation factors uniform in [1 - jitter, 1 + jitter] (rgb
        only). 0 disables it.
    confidence : (H, W) float32, 0..1, optional
        Confidence of the sparse depth: resized (nearest, like the depth it describes, but
        not divided by s), cropped and flipped with the other maps.

    Returns
    -------
    rgb : (h, w, 3) float32, 0..1
    sparse, gt : (h, w) float32, metres
    confidence : (h, w) float32
        Only when ``confidence`` is given (a fourth element).
    """
    import cv2

    # Fixed draw order: the same rng state gives the same augmentation whatever the options
    # (with or without a confidence map).
    s = float(rng.uniform(*scale_range))
    do_flip = bool(rng.random() < 0.5)
    factors = rng.uniform(1.0 - jitter, 1.0 + jitter, size=3)

    rgb = rgb.astype(np.float32) / 255.0
    maps = [sparse, gt] if confidence is None else [sparse, gt, confidence]
    if s != 1.0:
        h, w = gt.shape
        nh, nw = round(h * s), round(w * s)
        rgb = cv2.resize(rgb, (nw, nh), interpolation=cv2.INTER_LINEAR)
        maps = [_resize_nearest(m, nh, nw) for m in maps]
        maps[0], maps[1] = maps[0] / np.float32(s), maps[1] / np.float32(s)  # depths only
    if crop is not None:
        rgb = bottom_centre_crop(rgb, *crop)
        maps = [bottom_centre_crop(m, *crop) for m in maps]
    if flip and do_flip:
        rgb = rgb[:, ::-1]
        maps = [m[:, ::-1] for m in maps]
    if jitter > 0:
        rgb = colour_jitter(rgb, factors)
    return (
        np.ascontiguousarray(rgb, dtype=np.float32),
        *(np.ascontiguousarray(m, dtype=np.float32) for m in maps),
    )


class DepthDataset(Dataset):
    """Samples of one split as tensors for training or evaluation.

    Parameters
    ----------
    path : path-like
        Dataset folder (``manifest.parquet``).
    split : str
        ``'train'``, ``'val'``, ``'test'`` or any split of the manifest.
    augment : bool
        Random augmentation (training); otherwise only the optional crop.
    crop : (height, width) or None
        Bottom-centre crop (training and evaluation alike).
    seed : int
        Seed of the augmentation (with the epoch and the sample index).
    need_gt : bool
        Refuse a split without ground truth (:func:`open_split`).
    scale_range, jitter : see :func:`augment_sample`.
    input_mode : str, optional
        The network input the samples are for. ``'rgbdc'`` (:data:`CONFIDENCE_MODES`) loads
        the confidence maps too and refuses, here, a split where a sample has none
        (:func:`check_confidence`).
    densifier : LearnedDensifier, optional
        URL (input mode ``'rgbdu'``): computes each item's ``D_c`` and ``U`` from its sparse
        map as the network sees it (augmented, cropped), under ``torch.inference_mode``: a
        deterministic function of that map (:mod:`sparsetools.train.url`).

    Each item is a dict: ``rgb`` (3, h, w) float32 0..1, ``sparse`` and ``gt`` (1, h, w)
    float32 metres (``gt`` zeros when the sample has none), ``index`` (int), for
    ``rgbdc`` ``confidence`` (1, h, w) float32 0..1, and with a ``densifier`` ``coarse``
    (1, h, w) float32 metres and ``log_var`` (1, h, w) float32 log of square metres.
    """

    def __init__(
        self,
        path,
        split: str,
        *,
        augment: bool = False,
        crop: tuple[int, int] | None = None,
        seed: int = 0,
        need_gt: bool = True,
        scale_range: tuple[float, float] = (1.0, 1.0),
        jitter: float = 0.2,
        input_mode: str | None = None,
        densifier=None,
    ):
        self.reader = open_split(path, split, need_gt=need_gt)
        self.densifier = densifier
        self.with_confidence = input_mode in CONFIDENCE_MODES
        if self.with_confidence:
            check_confidence(self.reader, split=split, input_mode=input_mode)
        self.augment = bool(augment)
        self.crop = None if crop is None else (int(crop[0]), int(crop[1]))
        self.seed = int(seed)
        self.epoch = 0
        self.scale_range = (float(scale_range[0]), float(scale_range[1]))
        self.jitter = float(jitter)
        if not 0 < self.scale_range[0] <= self.scale_range[1]:
            raise ParameterError(f"scale range must satisfy 0 < low <= high, got {scale_range}")
        if self.scale_range != (1.0, 1.0) and (crop is None or self.scale_range[0] < 1.0):
            raise ParameterError("scale augmentation needs a crop and scales >= 1")
        check_crop(self.crop, self.sizes(), split)

    def __len__(self) -> int:
        return len(self.reader)

    def sizes(self) -> list[tuple[int, int]]:
        """(height, width) of every sample, from the manifest."""
        m = self.reader.manifest
        return list(zip(m.column("height").to_pylist(), m.column("width").to_pylist(), strict=True))

    def output_sizes(self) -> set[tuple[int, int]]:
        """The distinct (height, width) of the tensors this dataset yields."""
        if self.crop is not None:
            return {self.crop}
        return set(self.sizes())

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation stream of ``epoch`` (call before iterating each epoch)."""
        self.epoch = int(epoch)

    def sample_id(self, index: int) -> str:
        return self.reader.row(index)["id"]

    def _confidence_of(self, sample: dict) -> np.ndarray:
        conf = sample["confidence"]
        if conf is None:  # the manifest changed after the check in __init__
            raise FormatError(f"sample '{sample['id']}' has no confidence map")
        if not np.isfinite(conf).all():
            raise FormatError(f"sample '{sample['id']}': its confidence map holds NaN or Inf")
        return conf

    def __getitem__(self, index: int) -> dict:
        s = self.reader.sample(int(index))
        rgb, sparse = s["rgb"], s["sparse"]
        gt = s["gt"] if s["gt"] is not None else np.zeros(sparse.shape, np.float32)
        maps = [sparse, gt]
        if self.with_confidence:
            maps.append(self._confidence_of(s))
        if self.augment:
            rng = np.random.default_rng([self.seed, self.epoch, int(index)])
            rgb, *maps = augment_sample(
                rgb,
                sparse,
                gt,
                rng,
                crop=self.crop,
                scale_range=self.scale_range,
                jitter=self.jitter,
                confidence=maps[2] if self.with_confidence else None,
            )
        else:
            rgb = rgb.astype(np.float32) / 255.0
            if self.crop is not None:
                rgb = bottom_centre_crop(rgb, *self.crop)
                maps = [bottom_centre_crop(m, *self.crop) for m in maps]
        item = {
            "rgb": torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1))),
            "sparse": torch.from_numpy(np.ascontiguousarray(maps[0])[None]),
            "gt": torch.from_numpy(np.ascontiguousarray(maps[1])[None]),
            "index": int(index),
        }
        if self.with_confidence:
            item["confidence"] = torch.from_numpy(np.ascontiguousarray(maps[2], np.float32)[None])
        if self.densifier is not None:
            coarse, log_var = self.densifier.densify(maps[0])
            item["coarse"] = torch.from_numpy(coarse[None])
            item["log_var"] = torch.from_numpy(log_var[None])
        return item


#: The 4x4 transforms a :class:`SampleDataset` item carries (NaN where not stored).
TRANSFORMS = ("T_cam_lidar", "T_ego_cam", "T_world_ego", "T_world_cam")


class SampleDataset(Dataset):
    """Every sample of a dataset (or one split) as tensors, with its geometry: the loading
    recipe of docs/dataset.md, for a model of your own (no augmentation, no checks for
    training).

    Parameters
    ----------
    path : path-like
        Dataset folder.
    split : str, optional
        Only this split.

    Each item is a dict that ``torch.utils.data.default_collate`` stacks:

    - ``rgb`` (3, H, W) float32 0..1; ``sparse``, ``gt`` (1, H, W) float32 metres (``gt``
      zeros for a sample without ground truth) and ``has_gt`` (bool);
    - ``K`` (3, 3) float32 pixels, NaN where the dataset has no intrinsics;
    - ``T_cam_lidar``, ``T_ego_cam``, ``T_world_ego``, ``T_world_cam`` (4, 4) float64
      metres and ``baseline_m`` (float64), NaN where not stored (datasets built without
      ``--store-geometry``, schema 2), so that samples with and without them batch together;
    - ``index`` (int), ``id`` and ``camera`` (str; ``""`` in a one-camera dataset).

    The reader it holds pickles without its open files, so ``DataLoader(num_workers=N)``
    works and gives the same tensors as ``num_workers=0``.
    """

    def __init__(self, path, split: str | None = None):
        from ..io.dataset_reader import DatasetReader

        self.reader = DatasetReader(path, split=split)

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, index: int) -> dict:
        s = self.reader.sample(int(index))
        sparse = s["sparse"]
        gt = s["gt"]
        K = s["intrinsics"]
        item = {
            "rgb": torch.from_numpy(np.ascontiguousarray(s["rgb"].transpose(2, 0, 1))).float()
            / 255.0,
            "sparse": torch.from_numpy(sparse)[None],
            "gt": torch.from_numpy(gt if gt is not None else np.zeros_like(sparse))[None],
            "has_gt": gt is not None,
            "K": torch.full((3, 3), float("nan")) if K is None else torch.from_numpy(K).float(),
        }
        for name in TRANSFORMS:
            T = s[name]
            item[name] = (
                torch.full((4, 4), float("nan"), dtype=torch.float64)
                if T is None
                else torch.from_numpy(T)
            )
        b = s["baseline_m"]
        item["baseline_m"] = torch.tensor(float("nan") if b is None else b, dtype=torch.float64)
        item.update(index=int(index), id=s["id"], camera=s["camera"] or "")
        return item


def collate(items: list[dict]) -> dict:
    """Stack the items of a dataset (:class:`DepthDataset`, the triplets of
    :class:`~sparsetools.train.selfsup.data.TripletDataset`) into a batch.

    Every tensor entry is stacked along a new first axis and every integer entry (``index``)
    becomes a (B,) int64 tensor; the keys are those of the first item.

    Raises
    ------
    ParameterError
        Items of different image sizes (a tensor entry whose shapes differ).
    """
    batch = {}
    for key, first in items[0].items():
        if not isinstance(first, torch.Tensor):
            batch[key] = torch.tensor([it[key] for it in items], dtype=torch.long)
            continue
        if any(it[key].shape != first.shape for it in items):
            sizes = sorted({tuple(it[key].shape[-2:]) for it in items})
            listed = ", ".join(f"{w}x{h}" for h, w in sizes)
            raise ParameterError(
                f"images of different sizes in one batch ({listed}, WxH): use --crop-size WxH "
                "or a dataset with one image size",
                param="--crop-size",
            )
        batch[key] = torch.stack([it[key] for it in items])
    return batch
