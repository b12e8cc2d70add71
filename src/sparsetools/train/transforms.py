"""Load-time transforms of stored points (``dataset kitti-raw --store-points``).

:class:`RandomBeams` draws, per sample, how many beams of the stored scan to keep (e.g. 1, 2,
4 or 16 of 64), keeps the points of those rings and re-projects them with the sample's ``K``
into a sparse depth map: the beam-count augmentation of training on several LiDAR densities,
without building one dataset per count. :func:`reproject` is the projection alone: with the
stored points and ``K`` of a sample it gives back the sample's own sparse map (at the stored
size) bit for bit (tests/test_dataset_rig.py), or a map at another size with a scaled ``K``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..errors import ParameterError

__all__ = ["RandomBeams", "reproject"]


def reproject(xyz: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Camera-frame points to a sparse depth map, nearest point per pixel.

    Parameters
    ----------
    xyz : (N, 3) float64, metres
        Points in the camera frame (:meth:`DatasetReader.points`).
    K : (3, 3) float
        Intrinsics of the map, pixels.
    height, width : int

    Returns
    -------
    (height, width) float32, metres, 0 = empty: :func:`sparsetools.ops.projection.project_points`
    of the points with ``K`` and the identity transform (its min_depth 0.1 m and z-buffer).
    """
    from ..calibration import Calibration
    from ..ops.projection import project_points

    calib = Calibration(K=np.asarray(K, dtype=np.float64), T_cam_from_sensor=np.eye(4),
                        width=int(width), height=int(height))  # fmt: skip
    return project_points(np.asarray(xyz, dtype=np.float64), calib)


class RandomBeams:
    """Keep a random number of the scan's beams and re-project them.

    Parameters
    ----------
    keep : sequence of int
        The beam counts to draw from, uniformly (each must divide ``n_rings``).
    n_rings : int
        Rings of the stored scan (64 for KITTI's HDL-64E).
    seed : int, optional
        Seed of the draws; None: fresh entropy. With a :class:`numpy.random.Generator`
        passed to the call instead, the caller controls the stream (e.g. seeded by epoch and
        sample index, as :class:`~sparsetools.train.data.DepthDataset` does).

    Call ``transform(xyz, ring, K, height, width, rng=None)`` on a sample's stored points:
    returns ``(depth, rings)``, the (H, W) float32 sparse map of the kept points and the tuple
    of rings kept: every ``n_rings / n``-th ring from a random first one (``n`` drawn from
    ``keep``), as ``sparsetools beams --n`` keeps every (L/N)-th ring from ring 0.
    """

    def __init__(self, keep: Sequence[int] = (1, 2, 4, 16), *, n_rings: int = 64, seed=None):
        keep = tuple(int(k) for k in keep)
        if not keep or any(k < 1 or n_rings % k for k in keep):
            raise ParameterError(f"every beam count of keep must divide {n_rings}, got {keep}")
        self.keep = keep
        self.n_rings = int(n_rings)
        self._rng = np.random.default_rng(seed)

    def rings(self, rng: np.random.Generator | None = None) -> tuple[int, ...]:
        """Draw the rings to keep."""
        rng = rng or self._rng
        n = self.keep[int(rng.integers(len(self.keep)))]
        step = self.n_rings // n
        first = int(rng.integers(step))
        return tuple(range(first, self.n_rings, step))

    def __call__(self, xyz, ring, K, height, width, rng=None):
        if ring is None:
            raise ParameterError("RandomBeams needs the points' rings (none stored)")
        kept = self.rings(rng)
        mask = np.isin(np.asarray(ring), kept)
        return reproject(np.asarray(xyz)[mask], K, height, width), kept
