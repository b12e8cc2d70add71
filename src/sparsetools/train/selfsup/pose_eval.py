"""Pose accuracy of a self-supervised model: ATE over 5-frame snippets (monodepth2, KITTI odometry).

For every run of 5 consecutive frames of a sequence whose true poses are known (manifest
column ``T_world_cam``, camera-to-world), the pose network predicts the 4 motions between
consecutive frames (``T_k_to_k+1``, fed in time order); chaining them gives the predicted
camera positions in the snippet's first camera, ``C_k+1 = C_k inv(T_k_to_k+1)``, ``C_0 = I``.
The true positions are those of ``inv(G_0) G_k``. Then, as monodepth2's ``compute_ate``:

- the first positions are aligned (both are the origin here, so the offset is 0);
- the prediction is scaled by the least-squares factor ``s = sum(g . p) / sum(p . p)``
  (camera-only models know the motion only up to scale);
- ``ATE = sqrt(sum_k |s p_k - g_k|^2) / N`` with N = 5 (monodepth2 divides the root of the sum
  by N rather than taking the root of the mean; the same is done here so numbers compare).

The result is the mean and standard deviation over all snippets, in metres. Two more figures
come with it: the same ATE without the scale (``s = 1``: what a metric model, trained with the
sparse loss, claims), and the ATE of a network that predicts no motion (``p = 0``, the
"standing still" baseline): with the optimal scale no prediction does worse, so
``ate_mean / ate_still_mean`` is 0 for a perfect pose network and 1 for one that explains
none of the motion (training flags a run above ``pose_failure_ratio`` of it). Frames are fed at
their full size (no crop), with their sparse depth when the pose network has a LiDAR branch. One difference from monodepth2's script: it chains the forward
transforms themselves (``cam_to_world = cam_to_world @ T``, for prediction and ground truth
alike), which gives the translations of the inverse motions rather than the camera positions;
for the small rotations between video frames the two agree closely, and the positions used
here are the physical ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ...errors import ParameterError
from ..data import open_split
from .data import frame_poses, frame_sparse, sequence_frames
from .pose_net import PoseNet

__all__ = ["SNIPPET_LENGTH", "PoseAccuracy", "evaluate_pose", "snippet_ate", "snippet_positions"]

#: Frames per snippet (monodepth2 on KITTI odometry sequences 09 and 10).
SNIPPET_LENGTH = 5


@dataclass(frozen=True)
class PoseAccuracy:
    """ATE of the pose network: mean and standard deviation over snippets, metres."""

    ate_mean: float
    ate_std: float
    n_snippets: int
    snippet_length: int
    n_sequences: int
    #: without the per-snippet scale (metric models)
    ate_unscaled_mean: float = float("nan")
    ate_unscaled_std: float = float("nan")
    #: of predicting no motion (the positions all at the origin)
    ate_still_mean: float = float("nan")

    @property
    def still_ratio(self) -> float:
        """``ate_mean / ate_still_mean``: 0 = perfect, 1 = no motion explained."""
        return self.ate_mean / self.ate_still_mean if self.ate_still_mean > 0 else float("nan")


def snippet_positions(transforms: list[np.ndarray]) -> np.ndarray:
    """Camera positions of a snippet in its first camera's frame.

    Parameters
    ----------
    transforms : list of (4, 4) float
        ``T_k_to_k+1`` (points of camera k in camera k + 1), k = 0..N-2.

    Returns
    -------
    (N, 3) float64, metres; row 0 is the origin.
    """
    C = np.eye(4)
    out = [C[:3, 3].copy()]
    for T in transforms:
        C = C @ np.linalg.inv(np.asarray(T, np.float64))
        out.append(C[:3, 3].copy())
    return np.array(out)


def snippet_ate(predicted: np.ndarray, true: np.ndarray, *, scaled: bool = True) -> float:
    """monodepth2's ATE of one snippet: first frames aligned, optimal scale, sqrt(sum) / N.

    Parameters
    ----------
    predicted, true : (N, 3) float, camera positions
    scaled : bool
        Fit the least-squares scale (monodepth2); False: as predicted (metric models).
    """
    p = np.asarray(predicted, np.float64)
    g = np.asarray(true, np.float64)
    if p.shape != g.shape or p.ndim != 2 or p.shape[1] != 3 or len(p) < 2:
        raise ParameterError(f"need two (N, 3) trajectories of N >= 2, got {p.shape}, {g.shape}")
    p = p + (g[0] - p[0])
    denom = float(np.sum(p * p))
    scale = 1.0
    if scaled:
        scale = float(np.sum(g * p)) / denom if denom > 0 else 0.0
    return float(np.sqrt(np.sum((scale * p - g) ** 2)) / len(g))


def _consecutive_runs(reader, poses) -> list[list[int]]:
    """Runs of frames (positions) that are consecutive and all have a true pose."""
    index = None
    if "frame_index" in reader.manifest.column_names:
        values = reader.manifest.column("frame_index").to_pylist()
        if not all(v is None for v in values):
            index = values
    runs = []
    for members in sequence_frames(reader).values():
        run: list[int] = []
        for i in members:
            breaks = poses[i] is None or (
                run and index is not None and index[i] - index[run[-1]] != 1
            )
            if breaks:
                if len(run) >= SNIPPET_LENGTH:
                    runs.append(run)
                run = [] if poses[i] is None else [i]
            else:
                run.append(i)
        if len(run) >= SNIPPET_LENGTH:
            runs.append(run)
    return runs


@torch.no_grad()
def evaluate_pose(
    pose_net: PoseNet,
    dataset,
    *,
    split: str,
    device: torch.device,
    batch_size: int = 8,
) -> PoseAccuracy | None:
    """ATE over 5-frame snippets of the split's sequences with true poses (None without any)."""
    from ...io.image import read_image

    reader = open_split(dataset, split, need_gt=False)
    poses = frame_poses(reader)
    runs = _consecutive_runs(reader, poses)
    if not runs:
        return None
    pose_net.eval()
    # anything with ``transform(frame_a, frame_b)`` is a pose network here
    uses_lidar = bool(getattr(pose_net, "uses_lidar", False))

    def frame(i):
        rgb = read_image(reader.rgb_path(i))  # in the dataset, or referenced
        return torch.from_numpy(rgb.astype(np.float32).transpose(2, 0, 1) / 255.0)

    errors, unscaled, still = [], [], []
    for run in runs:
        images = [frame(i) for i in run]
        lidar = [torch.from_numpy(frame_sparse(reader, i)) for i in run] if uses_lidar else []
        predicted = []
        for a in range(0, len(run) - 1, batch_size):
            b = min(a + batch_size, len(run) - 1)
            first = torch.stack(images[a:b]).to(device)
            second = torch.stack(images[a + 1 : b + 1]).to(device)
            if lidar:
                pair = torch.stack(
                    [torch.stack(lidar[a:b]), torch.stack(lidar[a + 1 : b + 1])], dim=1
                ).to(device)
                T = pose_net.transform(first, second, pair)
            else:
                T = pose_net.transform(first, second)
            predicted += list(T.double().cpu().numpy())
        for j in range(len(run) - SNIPPET_LENGTH + 1):
            pred = snippet_positions(predicted[j : j + SNIPPET_LENGTH - 1])
            G0 = np.linalg.inv(poses[run[j]])
            true = np.array([(G0 @ poses[run[j + k]])[:3, 3] for k in range(SNIPPET_LENGTH)])
            errors.append(snippet_ate(pred, true))
            unscaled.append(snippet_ate(pred, true, scaled=False))
            still.append(snippet_ate(np.zeros_like(true), true, scaled=False))
    e, u = np.array(errors), np.array(unscaled)
    return PoseAccuracy(
        ate_mean=float(e.mean()),
        ate_std=float(e.std()),
        n_snippets=len(e),
        snippet_length=SNIPPET_LENGTH,
        n_sequences=len(runs),
        ate_unscaled_mean=float(u.mean()),
        ate_unscaled_std=float(u.std()),
        ate_still_mean=float(np.mean(still)),
    )
