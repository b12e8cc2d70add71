"""The unpaired reference depths of PBR (``train --self-supervised --pbr REFERENCE``).

REFERENCE is a dataset as ``sparsetools dataset build`` writes it. Its depth maps are drawn at
random for every training step, never matched with the training frames (unpaired):

- which samples: those of the split named like the run's ``--train-split`` when REFERENCE has
  one (so that the reference never brings in another split's ground truth when it is the
  training dataset itself), else every sample;
- which map: the sample's ground truth (``gt_path``); a sample without one gives its sparse
  depth when that is dense (``density`` at least :data:`DENSE_DENSITY`, e.g. a dataset built
  from ``densify`` output); others are not used;
- framing: the maps get the training frames' bottom-centre crop to the training size
  (``--crop-size``, else the frames' own size) and one horizontal flip decision each, as the
  training frames do, so the coordinate input I_p means the same in both; a reference frame
  smaller than the training size is refused;
- validity: 0 < depth < ``max_depth`` (the run's ``--max-depth``) and finite.

Draw ``k`` of a step comes from ``(seed, step)`` alone: a run resumed in the middle of an epoch
draws what the uninterrupted run drew.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...errors import FormatError, ParameterError
from ..data import bottom_centre_crop

__all__ = ["DENSE_DENSITY", "REFERENCE_STREAM", "ReferenceDepths"]

#: A sample without ground truth serves with its sparse depth when at least this fraction of
#: its pixels has a value (a dense map, not a LiDAR scan).
DENSE_DENSITY = 0.5
#: Stream of the reference draws (:class:`numpy.random.SeedSequence` entropy with seed, step).
REFERENCE_STREAM = 130363


class ReferenceDepths:
    """Reference depth maps for PBR, drawn per training step.

    Parameters
    ----------
    path : path-like
        The reference dataset's folder.
    split : str
        The run's training split name (used when REFERENCE has a split of that name).
    size : (height, width)
        The training images' size after the crop, pixels.
    max_depth : float
        Depths at or beyond this (metres) count as unknown.
    seed : int

    Raises
    ------
    ParameterError
        The folder does not exist, or a usable reference frame is smaller than ``size``.
    FormatError
        Not a dataset (no readable manifest), or no sample with ground truth or dense depth.
    """

    def __init__(self, path, *, split: str, size: tuple[int, int], max_depth: float, seed: int):
        from ...io.dataset_reader import DatasetReader

        self.root = Path(path)
        if not self.root.is_dir():
            raise ParameterError(
                f"reference dataset {self.root} does not exist (or is not a folder)", param="pbr"
            )
        try:
            reader = DatasetReader(self.root)
        except FormatError as exc:
            raise FormatError(f"--pbr: {exc}") from exc
        if split in reader.splits:
            reader = reader.split(split)
        self.reader = reader
        self.size = (int(size[0]), int(size[1]))
        self.max_depth = float(max_depth)
        self.seed = int(seed)
        table = reader.manifest
        gt = table.column("gt_path").to_pylist()
        density = table.column("density").to_pylist()
        self.positions: list[int] = []
        self.from_gt: list[bool] = []
        for i, (g, d) in enumerate(zip(gt, density, strict=True)):
            if g is not None or (d is not None and d >= DENSE_DENSITY):
                self.positions.append(i)
                self.from_gt.append(g is not None)
        if not self.positions:
            where = f"split '{reader.split_name}' of " if reader.split_name else ""
            raise FormatError(
                f"--pbr: no sample of {where}{self.root} has depth to serve as reference "
                f"(ground truth, or sparse depth of density >= {DENSE_DENSITY:g}): build it "
                "with --gt, or from dense depth maps"
            )
        h, w = self.size
        heights = table.column("height").to_pylist()
        widths = table.column("width").to_pylist()
        small = [i for i in self.positions if heights[i] < h or widths[i] < w]
        if small:
            i = small[0]
            raise ParameterError(
                f"{len(small)} of the {len(self.positions)} reference frames of {self.root} "
                f"are smaller than the {w}x{h} (WxH) training images (e.g. "
                f"{widths[i]}x{heights[i]}): PBR crops them as the training frames are cropped",
                param="pbr",
            )

    def __len__(self) -> int:
        return len(self.positions)

    def _map(self, k: int) -> np.ndarray:
        """Reference ``k``'s full-size depth (H, W) float32 metres, 0 = unknown."""
        from ...io.dataset import points_to_depth
        from ...io.depth_files import read_depth_file

        position = self.positions[k]
        row = self.reader.row(position)
        if self.from_gt[k]:
            depth = read_depth_file(self.reader.path(row.gt_path, what="gt_path"))
        else:
            u, v, d = self.reader.sparse_points(position)
            depth = points_to_depth(u, v, d, row.height, row.width)
        if depth.shape != (row.height, row.width):
            raise FormatError(
                f"--pbr: sample '{row.id}' of {self.root}: depth is "
                f"{depth.shape[1]}x{depth.shape[0]}, the manifest says {row.width}x{row.height}"
            )
        return depth

    def draw(self, *, step: int, batch: int) -> torch.Tensor:
        """The ``batch`` reference maps of training step ``step``.

        Returns
        -------
        (batch, 1, height, width) float32, metres
            Cropped and flipped as training frames are; 0 where the depth is unknown or
            not below ``max_depth``.
        """
        entropy = [self.seed % 2**32, REFERENCE_STREAM, int(step)]
        rng = np.random.default_rng(np.random.SeedSequence(entropy))
        picks = rng.integers(0, len(self.positions), size=batch)
        flips = rng.random(batch) < 0.5
        h, w = self.size
        out = np.zeros((batch, 1, h, w), np.float32)
        for b, (k, flip) in enumerate(zip(picks, flips, strict=True)):
            depth = bottom_centre_crop(self._map(int(k)), h, w)
            if flip:
                depth = depth[:, ::-1]
            ok = np.isfinite(depth) & (depth > 0) & (depth < self.max_depth)
            out[b, 0] = np.where(ok, depth, 0.0)
        return torch.from_numpy(out)
