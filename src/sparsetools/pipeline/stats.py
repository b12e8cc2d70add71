"""``sparsetools stats``: statistics of depth-map files, optionally against reference maps."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..errors import FormatError, ParameterError

__all__ = ["depth_stats_files"]


# -- stats over files ---------------------------------------------------------------------------
def _depth_files(path: str | os.PathLike, option: str) -> dict:
    """Depth maps by frame key: a file, a folder tree, or a folder written by sparsetools
    (its recorded depth maps only: confidence maps and calibrations are not frames)."""
    from ..io.sources import index_input

    p = Path(path)
    if p.is_file():
        from ..io.sources import FrameKey
        from ..io.sources.tree import file_stem

        return {FrameKey("", file_stem(p)): p}
    try:
        return index_input(p, "depth", option=option).files
    except FormatError as exc:
        raise ParameterError(f"{p}: no depth maps (.png or .npy)") from exc


def depth_stats_files(
    depth: str | os.PathLike,
    *,
    reference: str | os.PathLike | None = None,
    max_depth: float = 80.0,
) -> dict:
    """Statistics of one depth map or a folder of them, optionally against a reference.

    Parameters
    ----------
    depth : path-like
        A depth map (KITTI PNG or .npy) or a folder of them.
    reference : path-like, optional
        A reference map (e.g. LiDAR) or folder, matched by key/stem: adds the intrinsic-error
        metrics of each map against it.
    max_depth : float, metres
        Reference depths above this are ignored by the intrinsic error.

    Returns
    -------
    dict
        ``frames``: per-frame dicts (id, points, pixels, density_percent, min, median, mean,
        max, and with a reference :func:`sparsetools.ops.intrinsic.intrinsic_error`'s
        delta1, delta2, rmse, density (%), evaluated); ``aggregate``: per-frame values
        averaged over frames (min / max: over all frames) plus ``frames`` and
        ``total_points``; ``unmatched``: maps without a reference (left out).
    """
    from ..io.depth_files import read_depth_file
    from ..io.sources import match_keys
    from ..ops.intrinsic import intrinsic_error
    from ..ops.stats import depth_stats

    files = _depth_files(depth, "DEPTH")
    refs = None
    if reference is not None:
        refs = match_keys(files, _depth_files(reference, "--reference"))
        if not refs:
            raise ParameterError(
                f"no depth map in {depth} has a reference in {reference} with the same name"
            )
    frames = []
    for key in sorted(files):
        d = read_depth_file(files[key])
        rec = {"id": str(key), **depth_stats(d)}
        if refs is not None:
            if key not in refs:
                continue
            ref = read_depth_file(refs[key])
            if ref.shape != d.shape:
                raise FormatError(
                    f"{files[key]} is {d.shape[1]}x{d.shape[0]} but its reference {refs[key]} is "
                    f"{ref.shape[1]}x{ref.shape[0]}"
                )
            rec.update(intrinsic_error(d, ref, max_depth=max_depth))
        frames.append(rec)
    agg: dict = {"frames": len(frames), "total_points": int(sum(f["points"] for f in frames))}
    numeric = [k for k in (frames[0] if frames else {}) if k not in ("id", "pixels")]
    for k in numeric:
        vals = [f[k] for f in frames if isinstance(f.get(k), (int, float)) and math.isfinite(f[k])]
        if not vals:
            agg[k] = None
        elif k == "min":
            agg[k] = min(vals)
        elif k == "max":
            agg[k] = max(vals)
        else:  # per-frame values averaged over frames (the papers' tables do the same)
            agg[k] = float(np.mean(vals))
    result = {"frames": frames, "aggregate": agg}
    if refs is not None:
        result["unmatched"] = len(files) - len(frames)
    return result
