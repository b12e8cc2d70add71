"""Frame triplets (t-1, t, t+1) of a dataset's sequences, for self-supervised training.

Order and neighbours (from the manifest, read through :class:`~sparsetools.io.dataset.DatasetReader`):

- frames are grouped by the ``sequence`` column; neighbours never cross sequences;
- within a sequence, frames are ordered by the ``frame_index`` column (int) when the manifest
  has it (and it is set), else by the natural order of ``frame`` (``f2`` before ``f10``);
- with ``frame_index`` the neighbours of frame i are the frames with index i - 1 and i + 1
  (a gap in the numbering breaks the triplet); without it, the adjacent frames in that order;
- a frame is a training target when both neighbours exist; intrinsics come from the target's
  ``fx, fy, cx, cy`` (the three frames share one camera);
- ``T_world_cam`` (list of 16 floats, row-major camera-to-world 4x4, null when unknown), when
  present, gives the true poses (pose evaluation, :mod:`.pose_eval`).

Augmentation (training only; randomness from ``(seed, epoch, index)`` as in supervised
training, so results do not depend on the worker count): one horizontal flip decision and one
set of colour-jitter factors per triplet, applied to all three frames. Colour jitter changes
only the networks' inputs; the photometric loss sees the frames without it (monodepth2). The
intrinsics follow the crop (``c' = c - offset``) and the flip (``cx' = w - 1 - cx``).

Option ``sparse_frames`` (a pose network with a LiDAR branch): the sparse depth of all three
frames, cropped and flipped with them.

Night option ``mcie`` (RNW): the MCIE table is built from the target frame
(:func:`sparsetools.ops.enhance.mcie_lut`) and applied to all three frames; the enhanced frames
are what the photometric loss compares.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset

from ...errors import FormatError, ParameterError
from ..data import bottom_centre_crop, check_crop, colour_jitter, open_split

__all__ = [
    "Triplet",
    "TripletDataset",
    "frame_poses",
    "frame_sparse",
    "frame_triplets",
    "natural_key",
    "sequence_frames",
]


@dataclass(frozen=True)
class Triplet:
    """Positions (in the split's reader) of a target frame and its two neighbours."""

    previous: int
    target: int
    following: int


def natural_key(name: str) -> tuple:
    """Sort key that orders digit runs by value: ``f2`` < ``f10``, ``0009`` < ``0010``."""
    return tuple(
        (0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name) if t
    )


def _frame_indices(reader) -> list[int] | None:
    if "frame_index" not in reader.manifest.column_names:
        return None
    values = reader.manifest.column("frame_index").to_pylist()
    if all(v is None for v in values):
        return None
    if any(v is None for v in values):
        missing = next(reader.row(i)["id"] for i, v in enumerate(values) if v is None)
        raise FormatError(f"{reader.root}: frame_index is set for some frames but not '{missing}'")
    return [int(v) for v in values]


def sequence_frames(reader) -> dict[str, list[int]]:
    """Positions of each sequence's frames in time order.

    Raises
    ------
    FormatError
        Two frames of one sequence with the same ``frame_index``, or ``frame_index`` null for
        some frames only.
    """
    index = _frame_indices(reader)
    groups: dict[str, list[int]] = {}
    for i, seq in enumerate(reader.manifest.column("sequence").to_pylist()):
        groups.setdefault(seq, []).append(i)
    frames = reader.manifest.column("frame").to_pylist()
    out = {}
    for seq, members in groups.items():
        if index is None:
            members = sorted(members, key=lambda i: natural_key(frames[i]))
        else:
            members = sorted(members, key=lambda i: index[i])
            values = [index[i] for i in members]
            if len(set(values)) != len(values):
                dup = next(v for v in values if values.count(v) > 1)
                raise FormatError(
                    f"{reader.root}: sequence '{seq}' has two frames with frame_index {dup}"
                )
        out[seq] = members
    return out


def frame_triplets(reader) -> list[Triplet]:
    """Every frame with both neighbours in its sequence, as a :class:`Triplet` (time order)."""
    index = _frame_indices(reader)
    triplets = []
    for members in sequence_frames(reader).values():
        for a, b, c in zip(members, members[1:], members[2:], strict=False):
            if index is not None and not (index[b] - index[a] == 1 and index[c] - index[b] == 1):
                continue
            triplets.append(Triplet(a, b, c))
    return triplets


def frame_poses(reader) -> list[np.ndarray | None]:
    """True camera-to-world poses (4, 4) float64 per frame, None where unknown (or no column).

    Raises
    ------
    FormatError
        A pose that is not 16 finite numbers with last row ``0 0 0 1``.
    """
    if "T_world_cam" not in reader.manifest.column_names:
        return [None] * len(reader)
    out: list[np.ndarray | None] = []
    for sample_id, values in zip(
        reader.manifest.column("id").to_pylist(),
        reader.manifest.column("T_world_cam").to_pylist(),
        strict=True,
    ):
        if values is None:
            out.append(None)
            continue
        T = np.asarray(values, dtype=np.float64)
        if T.shape != (16,) or not np.all(np.isfinite(T)):
            raise FormatError(f"sample '{sample_id}': T_world_cam must be 16 finite numbers")
        T = T.reshape(4, 4)
        if np.abs(T[3] - (0, 0, 0, 1)).max() > 1e-9:
            raise FormatError(f"sample '{sample_id}': T_world_cam's last row is not 0 0 0 1")
        out.append(T)
    return out


def frame_sparse(reader, position: int) -> np.ndarray:
    """(H, W) float32 sparse depth (metres, 0 = empty) of one frame, without its image.

    Raises
    ------
    FormatError
        The frame has no sparse depth.
    """
    from ...io.dataset import points_to_depth

    row = reader.row(position)
    if row["sparse_path"] is None and row["sparse_parquet"] is None:
        raise FormatError(
            f"sample '{row['id']}' has no sparse depth: a LiDAR encoder needs it for every frame"
        )
    u, v, depth = reader.sparse_points(position)
    return points_to_depth(u, v, depth, row["height"], row["width"])


def _intrinsics(row: dict) -> np.ndarray:
    if any(row[k] is None for k in ("fx", "fy", "cx", "cy")):
        raise FormatError(
            f"sample '{row['id']}' has no intrinsics (fx, fy, cx, cy): self-supervised training "
            "needs them; build the dataset with --calib"
        )
    return np.array(
        [[row["fx"], 0.0, row["cx"]], [0.0, row["fy"], row["cy"]], [0.0, 0.0, 1.0]], np.float64
    )


class TripletDataset(Dataset):
    """The triplets of one split as tensors.

    Parameters
    ----------
    path : path-like
        Dataset folder.
    split : str
    augment : bool
        Flip and colour jitter (training).
    crop : (height, width) or None
        Bottom-centre crop of all three frames (training and evaluation alike).
    seed : int
    jitter : float
        Colour-jitter amplitude (factors uniform in [1 - jitter, 1 + jitter]).
    mcie : bool
        Photometric frames enhanced with one MCIE table per triplet (built from the target).
    mcie_clip : float
        MCIE clip limit.
    sparse_frames : bool
        Also yield the sparse depth of the three frames (``sparse_frames``).

    Each item is a dict: ``frames`` (3, 3, h, w) float32 0..1 [previous, target, following]
    as the photometric loss sees them; ``inputs`` (3, 3, h, w) float32 0..1 as the networks
    see them (jittered); ``sparse`` and ``gt`` (1, h, w) float32 metres of the target (zeros
    when absent); ``K`` (3, 3) float32; ``index`` (int); with ``sparse_frames``, also
    ``sparse_frames`` (3, h, w) float32 metres [previous, target, following].
    """

    def __init__(
        self,
        path,
        split: str,
        *,
        augment: bool = False,
        crop: tuple[int, int] | None = None,
        seed: int = 0,
        jitter: float = 0.2,
        mcie: bool = False,
        mcie_clip: float = 0.004,
        sparse_frames: bool = False,
    ):
        self.reader = open_split(path, split, need_gt=False)
        self.triplets = frame_triplets(self.reader)
        if not self.triplets:
            raise ParameterError(
                f"split '{split}' of {path} has no frame with both neighbours in its sequence: "
                "self-supervised training needs sequences of 3 or more consecutive frames"
            )
        self.augment = bool(augment)
        self.crop = None if crop is None else (int(crop[0]), int(crop[1]))
        self.seed = int(seed)
        self.epoch = 0
        self.jitter = float(jitter)
        self.mcie = bool(mcie)
        self.mcie_clip = float(mcie_clip)
        self.sparse_frames = bool(sparse_frames)
        rows = [self.reader.row(i) for i in range(len(self.reader))]
        for t in self.triplets:
            _intrinsics(rows[t.target])
            sizes = {
                (rows[i]["height"], rows[i]["width"]) for i in (t.previous, t.target, t.following)
            }
            if len(sizes) > 1:
                raise FormatError(
                    f"frames around '{rows[t.target]['id']}' differ in size: one camera per sequence"
                )
        check_crop(self.crop, self.sizes(), split)

    def __len__(self) -> int:
        return len(self.triplets)

    def sizes(self) -> list[tuple[int, int]]:
        """(height, width) of every target frame."""
        rows = [self.reader.row(t.target) for t in self.triplets]
        return [(r["height"], r["width"]) for r in rows]

    def output_sizes(self) -> set[tuple[int, int]]:
        """The distinct (height, width) of the tensors this dataset yields."""
        return {self.crop} if self.crop is not None else set(self.sizes())

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation stream of ``epoch`` (call before iterating each epoch)."""
        self.epoch = int(epoch)

    def sample_id(self, index: int) -> str:
        """Id of the target frame of triplet ``index``."""
        return self.reader.row(self.triplets[index].target)["id"]

    def _rgb(self, position: int) -> np.ndarray:
        """The camera image of a frame alone (its neighbours' depth maps are not needed)."""
        from ...io.image import read_image

        row = self.reader.row(position)
        rgb = read_image(self.reader.rgb_path(position))  # in the dataset, or referenced
        if rgb.shape[:2] != (row["height"], row["width"]):
            raise FormatError(
                f"sample '{row['id']}': rgb is {rgb.shape[1]}x{rgb.shape[0]}, the manifest says "
                f"{row['width']}x{row['height']}"
            )
        return rgb

    def __getitem__(self, index: int) -> dict:
        from ...ops.enhance import apply_lut, mcie_lut

        t = self.triplets[int(index)]
        target = self.reader.sample(t.target)
        rgbs = [self._rgb(t.previous), target["rgb"], self._rgb(t.following)]
        sparse = target["sparse"]
        gt = target["gt"] if target["gt"] is not None else np.zeros(sparse.shape, np.float32)
        # the target's own map is the one in ``sparse``: the same values, read once
        lidar = (
            [frame_sparse(self.reader, t.previous), sparse, frame_sparse(self.reader, t.following)]
            if self.sparse_frames
            else []
        )
        K = _intrinsics(self.reader.row(t.target))
        if self.crop is not None:
            ch, cw = self.crop
            h, w = sparse.shape
            rgbs = [bottom_centre_crop(x, ch, cw) for x in rgbs]
            sparse, gt = bottom_centre_crop(sparse, ch, cw), bottom_centre_crop(gt, ch, cw)
            lidar = [bottom_centre_crop(x, ch, cw) for x in lidar]
            K[0, 2] -= (w - cw) // 2
            K[1, 2] -= h - ch
        # fixed draw order: the same generator state gives the same augmentation
        rng = np.random.default_rng([self.seed, self.epoch, int(index)])
        do_flip = bool(rng.random() < 0.5)
        factors = rng.uniform(1.0 - self.jitter, 1.0 + self.jitter, size=3)
        loss_rgbs = rgbs
        if self.mcie:
            lut = mcie_lut(rgbs[1], clip=self.mcie_clip)
            loss_rgbs = [apply_lut(x, lut) for x in rgbs]
        if self.augment and do_flip:
            rgbs, loss_rgbs = [x[:, ::-1] for x in rgbs], [x[:, ::-1] for x in loss_rgbs]
            sparse, gt = sparse[:, ::-1], gt[:, ::-1]
            lidar = [x[:, ::-1] for x in lidar]
            K[0, 2] = sparse.shape[1] - 1 - K[0, 2]
        frames = [x.astype(np.float32) / 255.0 for x in loss_rgbs]
        inputs = [x.astype(np.float32) / 255.0 for x in rgbs]
        if self.augment and self.jitter > 0:
            inputs = [colour_jitter(x, factors) for x in inputs]
        item = {
            "frames": torch.from_numpy(
                np.ascontiguousarray(np.stack(frames).transpose(0, 3, 1, 2))
            ),
            "inputs": torch.from_numpy(
                np.ascontiguousarray(np.stack(inputs).transpose(0, 3, 1, 2))
            ),
            "sparse": torch.from_numpy(np.ascontiguousarray(sparse, dtype=np.float32)[None]),
            "gt": torch.from_numpy(np.ascontiguousarray(gt, dtype=np.float32)[None]),
            "K": torch.from_numpy(K.astype(np.float32)),
            "index": int(index),
        }
        if self.sparse_frames:
            item["sparse_frames"] = torch.from_numpy(
                np.ascontiguousarray(np.stack(lidar), dtype=np.float32)
            )
        return item
