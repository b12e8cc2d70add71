"""``sparsetools stats``: points, density and depth range; intrinsic error against a reference."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from .options import json_option, max_depth_option, quiet_debug_options

_COLUMNS = (
    ("points", "points", "{:d}"),
    ("density_percent", "density %", "{:.3f}"),
    ("min", "min m", "{:.2f}"),
    ("median", "median m", "{:.2f}"),
    ("max", "max m", "{:.2f}"),
)
_ERROR_COLUMNS = (
    ("evaluated", "evaluated", "{:d}"),
    ("delta1", "delta1", "{:.4f}"),
    ("delta2", "delta2", "{:.4f}"),
    ("rmse", "RMSE m", "{:.3f}"),
)


def _cell(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if fmt.endswith("d}"):
        return fmt.format(round(value))
    return fmt.format(value)


@click.command("stats")
@click.argument("depth", type=click.Path(exists=True, path_type=Path))
@click.option(
    "--reference",
    type=click.Path(exists=True, path_type=Path),
    help="Reference depth map or folder (e.g. LiDAR), matched by file name: adds the "
    "intrinsic error (delta1, delta2, RMSE at pixels valid in both).",
)
@max_depth_option(default=80.0, help="Reference depths above this (m) are not evaluated.")
@json_option(help="Print per-frame and aggregate values as JSON.")
@quiet_debug_options
def stats(depth, reference, max_depth, as_json):
    """Points, density and depth range of depth maps; with --reference, intrinsic error.

    DEPTH is a KITTI uint16 depth PNG or .npy of metres, or a folder of them. The
    aggregate line averages the per-frame values (points, density, delta, RMSE) over frames;
    min/max are over all frames.

    \b
    Examples:
      sparsetools beams out/scene/velodyne --n 4 -o out/beams4
      sparsetools project out/beams4 --calib out/scene/calib --image-size 1242x375 \\
          -o out/depth4
      sparsetools stats out/depth4
      sparsetools stats out/jbf --reference out/lidar --json
    """
    from ..pipeline.stats import depth_stats_files

    result = depth_stats_files(depth, reference=reference, max_depth=max_depth)
    if as_json:
        click.echo(json.dumps(result, indent=1))
        return
    cols = list(_COLUMNS) + (list(_ERROR_COLUMNS) if reference is not None else [])
    rows = [[f["id"], *(_cell(f.get(k), fmt) for k, _, fmt in cols)] for f in result["frames"]]
    agg = result["aggregate"]
    if len(rows) > 1:
        rows.append([f"mean of {agg['frames']}", *(_cell(agg.get(k), fmt) for k, _, fmt in cols)])
    header = ["frame", *(title for _, title, _ in cols)]
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    for r in [header, *rows]:
        click.echo(
            "  ".join(
                str(c).rjust(w) if i else str(c).ljust(w)
                for i, (c, w) in enumerate(zip(r, widths, strict=True))
            )
        )
    if reference is not None and result.get("unmatched"):
        click.echo(
            f"{result['unmatched']} depth map(s) without a reference were left out", err=True
        )
