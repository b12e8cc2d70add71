"""``sparsetools accumulate``: KITTI-like semi-dense depth from the scans of t-K..t+K."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    build,
    calib_option,
    deprecated,
    emit_summary,
    filter_occluded_option,
    icp_min_range_option,
    image_option,
    image_size_option,
    max_depth_option,
    min_depth_option,
    non_negative,
    output_dir_option,
    pixel_offset_option,
    plot_option,
    positive,
    root_flag,
    verbose_option,
)


@click.command("accumulate")
@click.argument(
    "clouds",
    nargs=-1,
    required=True,
    metavar="CLOUD...",
    type=click.Path(exists=True, path_type=Path),
)
@output_dir_option
@calib_option
@image_size_option
@image_option
@click.option(
    "--neighbours",
    type=int,
    default=5,
    show_default=True,
    metavar="K",
    help="Merge frames t-K..t+K of the same sequence (0..100, clipped at its ends; KITTI's "
    "ground truth: 5, i.e. 11 scans).",
)
@click.option(
    "--poses",
    type=click.Path(exists=True, path_type=Path),
    help="KITTI odometry poses.txt (one sequence) or a folder of <sequence>.txt / "
    "<sequence>/poses.txt [default: the input's own: synthetic video, KITTI raw oxts, nuScenes].",
)
@click.option(
    "--poses-frame",
    type=click.Choice(["auto", "camera", "sensor"]),
    default="auto",
    show_default=True,
    help="What --poses holds: camera poses (KITTI odometry) or the LiDAR's; auto: sensor "
    "when the file name contains 'velodyne' or 'lidar'.",
)
@click.option(
    "--icp", is_flag=True, help="Poses by Open3D point-to-plane ICP between consecutive scans."
)
@icp_min_range_option
@click.option(
    "--icp-voxel", type=float, default=0.2, show_default=True, callback=positive,
    help="ICP: finest voxel size, metres.",
)  # fmt: skip
@click.option(
    "--icp-max-distance", type=float, default=0.5, show_default=True, callback=positive,
    help="ICP: finest correspondence distance, metres.",
)  # fmt: skip
@click.option(
    "--mask",
    type=click.Path(exists=True, path_type=Path),
    help="Moving-object masks of frame t (PNG, non-zero = moving) matched by frame, or a "
    "synthetic video folder (its moving_mask/): other scans' points there are dropped.",
)
@min_depth_option
@max_depth_option
@pixel_offset_option
@click.option(
    "--occlusion-rel", type=float, default=0.1, show_default=True, callback=non_negative,
    help="Drop other scans' points farther than (1 + this) x the nearest depth in their window.",
)  # fmt: skip
@click.option("--no-occlusion", is_flag=True, help="No occlusion test.")
@filter_occluded_option
@click.option(
    "--occlusion-foreground",
    type=click.Choice(["all", "own"]),
    default="all",
    show_default=True,
    help="Foreground of the occlusion test: frame t's and the other kept points, or frame t's.",
)
@click.option(
    "--consistency-rel", type=float, default=0.1, show_default=True, callback=non_negative,
    help="Drop other scans' points nearer than 1 / (1 + this) x all frame t measured near them.",
)  # fmt: skip
@click.option("--no-consistency", is_flag=True, help="No moving-object (consistency) test.")
@click.option(
    "--footprint-m", type=float, default=0.1, show_default=True, callback=positive,
    help="Half size of the test window in metres at the point's depth.",
)  # fmt: skip
@click.option(
    "--min-radius-px", type=click.IntRange(0, 64), default=1, show_default=True,
    help="Smallest test window radius, pixels.",
)  # fmt: skip
@click.option(
    "--max-radius-px", type=click.IntRange(0, 64), default=8, show_default=True,
    help="Largest test window radius, pixels.",
)  # fmt: skip
@plot_option(help="Also write OUT/removals.png: the points removed per frame, by reason "
             "(matplotlib: pip install 'sparsetools[viz]').")  # fmt: skip
@verbose_option
@deprecated("--window", "--neighbours", command="accumulate", dest="neighbours")
@batch_options
def accumulate(
    clouds,
    out_dir,
    calib,
    image_size,
    image,
    neighbours,
    poses,
    poses_frame,
    icp,
    icp_min_range,
    icp_voxel,
    icp_max_distance,
    mask,
    min_depth,
    max_depth,
    pixel_offset,
    occlusion_rel,
    no_occlusion,
    filter_occluded,
    occlusion_foreground,
    consistency_rel,
    no_consistency,
    footprint_m,
    min_radius_px,
    max_radius_px,
    plot,
    batch,
    as_json,
):
    """Merge the LiDAR scans of frames t-K..t+K into frame t's view (KITTI-style ground truth).

    CLOUD: scan files or folders, KITTI raw drives, a synthetic video folder (synth-scene
    --video) or a nuScenes root (LIDAR_TOP key frames). Each scan is moved into frame t with
    the frames' poses (--poses, the input's own, or --icp), projected, and the other scans'
    points that frame t cannot see are dropped: behind the local foreground (occluded),
    nearer than what frame t's own scan measured around them (inconsistent: moving objects)
    or inside --mask. Writes OUT/<sequence>/<frame>.png (KITTI uint16), the calibration as
    OUT/calib/<sequence>/<frame>.json and, with --icp, each pair's pose in
    OUT/icp/<sequence>/<frame>.json. The summary is one line (the totals with -v, and one
    line per frame with the removals by reason; everything, ICP's fitness per pair too, with
    --json); --plot draws the removals per frame as OUT/removals.png.
    A frame is recomputed when a scan of its window, its calibration or a pose file changed.

    \b
    Examples:
      sparsetools synth-scene -o out/video --video --static --sequences 1 --frames 12
      sparsetools accumulate out/video -o out/acc --neighbours 5
      sparsetools accumulate out/video -o out/acc --neighbours 5 --plot -v
      sparsetools accumulate ../shared/data/real/kitti-raw-sequence-2011_09_26 \\
          --icp --icp-min-range 20 --neighbours 5 -o out/acc_kitti
      sparsetools accumulate velodyne/ --calib calib/ --poses poses.txt -o out/acc
    """
    from ..ops.accumulate import AccumulateSettings
    from ..pipeline import run_job
    from ..pipeline.accumulate import AccumulateRunSettings, IcpSettings, accumulation_job

    icp_given = [
        name
        for name, value, default in (
            ("--icp-min-range", icp_min_range, 0.0),
            ("--icp-voxel", icp_voxel, 0.2),
            ("--icp-max-distance", icp_max_distance, 0.5),
        )
        if value != default
    ]
    if icp_given and not icp:
        raise click.UsageError(f"{icp_given[0]} goes with --icp")
    if icp and poses is not None:
        raise click.UsageError("give --poses or --icp, not both")
    if filter_occluded and no_occlusion:
        raise click.UsageError(
            "--filter-occluded applies the occlusion test: not with --no-occlusion"
        )
    if poses is None and poses_frame != "auto":
        raise click.UsageError("--poses-frame goes with --poses")
    if plot:
        from ..io.plots import require_matplotlib

        require_matplotlib("accumulate --plot")  # before any frame is computed
    geometry = build(
        AccumulateSettings,
        min_depth=min_depth,
        max_depth=max_depth,
        pixel_offset=int(pixel_offset),
        occlusion_rel=None if no_occlusion else occlusion_rel,
        occlusion_foreground=occlusion_foreground,
        consistency_rel=None if no_consistency else consistency_rel,
        footprint_m=footprint_m,
        min_radius_px=min_radius_px,
        max_radius_px=max_radius_px,
        occlude_own=filter_occluded,
    )
    icp_settings = build(IcpSettings, min_range=icp_min_range, voxel=icp_voxel,
                         max_distance=icp_max_distance)  # fmt: skip
    build(AccumulateRunSettings, window=neighbours)  # the range of K, before any input is read
    job, frames = accumulation_job(
        list(clouds), window=neighbours, accumulate=geometry, icp=icp, icp_settings=icp_settings,
        calib=calib, image=image, poses=poses, poses_frame=poses_frame, mask=mask,
        image_size=image_size,
    )  # fmt: skip
    summary = run_job(job, frames, out_dir, batch=batch,
                      inputs=[*clouds, calib, image, poses, mask])  # fmt: skip
    totals = summary.as_dict()
    if plot:
        from ..pipeline.plots import REMOVALS_PLOT, removal_panels, write_command_plot

        written = write_command_plot(out_dir / REMOVALS_PLOT, removal_panels(totals),
                                     command="accumulate --plot", overwrite=batch.overwrite,
                                     columns=1, panel_size=(900, 360))  # fmt: skip
        totals["plot"] = str(written)
    if as_json or root_flag("verbose"):
        if not as_json:
            for line in per_frame_lines(totals):
                click.echo(line)
        emit_summary(totals, as_json=as_json, title=f"accumulated depth maps in {out_dir}",
                     details=PER_FRAME)  # fmt: skip
    else:
        click.echo(summary_line(totals, out_dir))
        if totals.get("failed"):  # the failed frames listed, exit 1
            failed = {k: totals[k] for k in ("failed", "failures") if k in totals}
            emit_summary(failed, as_json=False)


def summary_line(totals: dict, out_dir) -> str:
    """accumulate's summary without ``-v``: one line whatever the number of frames."""
    removed = totals.get("removed") or {}
    reasons = ", ".join(f"{r} {removed.get(r, 0)}" for r in ("occluded", "inconsistent", "masked"))
    plot = f"; plot {totals['plot']}" if totals.get("plot") else ""
    return (
        f"accumulated {totals.get('processed', 0)} of {totals.get('frames', 0)} frames in "
        f"{out_dir} ({totals.get('skipped_existing', 0)} up to date, {totals.get('failed', 0)} "
        f"failed): density {totals.get('density_pct', 0.0):.4g} %, kept "
        f"{totals.get('kept', 0)} of {totals.get('points', 0)} points, removed {reasons}{plot} "
        "(-v: totals and per frame)"
    )


def per_frame_lines(totals: dict) -> list[str]:
    """``-v``: one line per frame, the other scans' points removed by reason."""
    clipped = totals.get("clipped_window_frames") or {}
    lines = []
    for fid, counts in (totals.get("removed_per_frame") or {}).items():
        text = ", ".join(f"{k} {v}" for k, v in counts.items())
        window = f" (window {clipped[fid]})" if fid in clipped else ""
        lines.append(f"{fid}: removed {text}{window}")
    return lines


#: Per-frame (per-pair) tables of the summary: in ``--json`` only (``-v`` prints the removals
#: per frame as lines of their own), so the totals have the same lines for 5 frames or 5,000.
PER_FRAME = ("removed_per_frame", "clipped_window_frames", "icp.per_pair")
