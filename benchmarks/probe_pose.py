"""Probe of a self-supervised run's pose (issue 24): can the photometric loss teach it?

For every validation triplet of a run's dataset, the per-pixel photometric error of the target
against its two neighbours (minimum over the sources, mean over the pixels with a valid warp),
with the run's own depth prediction and

- ``predicted``: the run's pose network (what training optimised);
- ``true_pose``: the true poses of the manifest (``T_world_cam``);
- ``no_warp``: the unwarped neighbours (the auto-mask's reference);

and, as a floor, ``true_both``: the true poses with the true depth (ground truth, where it
exists). If ``true_pose`` is well below ``predicted``, the loss surface pulls the pose network
toward the true motion and the network did not get there; if it is not, the depth is too wrong
for the true motion to explain the frames better, and the pose has nothing to learn from.

    .venv/bin/python benchmarks/probe_pose.py out/acceptance_claims/runs/ML/seed0 [...]

Prints one line per run (and ``--json`` the numbers).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def _error(frames, K, transforms, depth, where=None) -> float:
    """Mean over valid pixels of the minimum photometric error over the two sources."""
    from sparsetools.train.selfsup.geometry import warp_frame
    from sparsetools.train.selfsup.photometric import photometric_error

    target = frames[:, 1]
    errs, valid = [], []
    for k, T in zip((0, 2), transforms, strict=True):
        w = warp_frame(frames[:, k], depth, T.double(), K)
        errs.append(photometric_error(w.image, target))
        valid.append(w.in_front)
    e = torch.cat(errs, 1).min(1).values
    ok = torch.stack(valid, 0).any(0).reshape(e.shape)
    if where is not None:
        ok &= where.reshape(e.shape)
    return float(e[ok].mean())


def probe(run: Path) -> dict:
    from sparsetools.train.checkpoint import (
        load_checkpoint,
        model_from_checkpoint,
        pose_from_checkpoint,
    )
    from sparsetools.train.model import disparity_to_depth
    from sparsetools.train.selfsup.data import TripletDataset, frame_poses
    from sparsetools.train.selfsup.photometric import photometric_error
    from sparsetools.train.selfsup.pose_net import source_transforms

    ckpt = load_checkpoint(run / "best.pt")
    depth_net = model_from_checkpoint(ckpt).eval()
    pose_net = pose_from_checkpoint(ckpt).eval()
    config = ckpt.config
    val = TripletDataset(
        config.dataset, config.val_split, augment=False, sparse_frames=pose_net.uses_lidar
    )
    poses = frame_poses(val.reader)
    sums = {"predicted": [], "true_pose": [], "no_warp": [], "true_both": []}
    with torch.no_grad():
        for i, t in enumerate(val.triplets):
            item = val[i]
            frames = item["frames"][None].double()  # (1, 3, 3, H, W)
            inputs = item["inputs"][None]
            sparse = item["sparse"][None]
            K = item["K"][None].double()
            disp = depth_net.run(inputs[:, 1], sparse)[0]
            depth = disparity_to_depth(disp, *config.selfsup.depth_range).double()
            lidar = None
            if pose_net.uses_lidar:
                lidar = item["sparse_frames"][None]
            pred = source_transforms(
                pose_net, inputs[:, 0], inputs[:, 1], inputs[:, 2], lidar=lidar
            )
            g = [poses[t.previous], poses[t.target], poses[t.following]]
            true = [torch.from_numpy(np.linalg.inv(g[k]) @ g[1])[None] for k in (0, 2)]
            target = frames[:, 1]
            gt = item["gt"]

            sums["predicted"].append(_error(frames, K, pred, depth))
            sums["true_pose"].append(_error(frames, K, true, depth))
            ident = torch.cat([photometric_error(frames[:, k], target) for k in (0, 2)], 1)
            sums["no_warp"].append(float(ident.min(1).values.mean()))
            has_gt = gt[None] > 0
            if bool(has_gt.any()):  # where the ground truth has depth (not the sky)
                d = torch.where(has_gt, gt[None], torch.ones_like(gt[None])).double()
                sums["true_both"].append(_error(frames, K, true, d, has_gt))
    return {k: float(np.mean(v)) if v else float("nan") for k, v in sums.items()}


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = p.parse_args()
    torch.set_num_threads(1)
    out = {}
    print("run | photometric error: predicted pose | true pose | no warp | true pose + true depth")
    for run in args.runs:
        r = probe(run)
        out[str(run)] = r
        print(
            f"{run} | {r['predicted']:.4f} | {r['true_pose']:.4f} | {r['no_warp']:.4f} | "
            f"{r['true_both']:.4f}",
            flush=True,
        )
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
