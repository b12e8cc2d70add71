"""``sparsetools eval``: depth metrics of a trained checkpoint or of any method's depth PNGs."""

from __future__ import annotations

import json
from pathlib import Path

import click

from .options import (
    batch_size_option,
    device_option,
    json_option,
    max_depth_option,
    output_dir_option,
)
from .train import progress_wanted


@click.command("eval")
@click.argument(
    "dataset", required=False, type=click.Path(exists=True, file_okay=False, path_type=Path)
)
@click.option(
    "--checkpoint",
    type=click.Path(exists=True, path_type=Path),
    help="best.pt / last.pt of `sparsetools train` (or the run folder: its best.pt).",
)
@click.option(
    "--pred",
    "pred_dir",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Folder of predicted depth maps (KITTI uint16 PNG or .npy metres).",
)
@click.option(
    "--gt",
    "gt_dir",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Folder of ground-truth depth maps, matched to --pred by file stem.",
)
@click.option(
    "--split",
    default="test",
    show_default=True,
    help="Split of DATASET evaluated with --checkpoint.",
)
@click.option("--garg-crop", is_flag=True, help="Evaluate inside the Garg crop only (KITTI Eigen).")
@click.option(
    "--min-depth",
    type=click.FloatRange(min=0, min_open=True),
    default=1e-3,
    show_default=True,
    help="Ground truth at or below this (m) is not evaluated.",
)
@max_depth_option(default=80.0, help="Ground truth at or above this (m) is not evaluated.")
@click.option(
    "--scaling",
    type=click.Choice(["auto", "median", "none"]),
    default="auto",
    show_default=True,
    help="Per-image median scaling of the predictions. auto: median for camera-only "
    "self-supervised checkpoints (monodepth2's protocol), none for every other model and for "
    "--pred.",
)
@device_option
@batch_size_option(default=4)
@output_dir_option(
    required=False,
    file=True,
    help="Results file (.json or .csv; both are written). Default with --checkpoint: "
    "eval_<split>.json/.csv next to it; with --pred: none.",
)
@json_option(help="Print the results as JSON.")
def eval_(
    dataset,
    checkpoint,
    pred_dir,
    gt_dir,
    split,
    garg_crop,
    min_depth,
    max_depth,
    scaling,
    device,
    batch_size,
    out_dir,
    as_json,
):
    """Depth metrics per image, then averaged (AbsRel, SqRel, SqRel-KITTI, RMSE, RMSE log,
    SILog, delta1-3, MAE, iRMSE, iMAE) on pixels with min-depth < gt < max-depth.

    Camera-only self-supervised models are median-scaled per image (flagged in the output);
    for self-supervised models on sequences with true poses, also the pose ATE.

    \b
    Examples:
      sparsetools eval --checkpoint out/run/best.pt out/ds --split test
      sparsetools eval --pred results/depth --gt out/scene/depth_gt -o results/metrics.json
    """
    from ..train.evaluate import (
        evaluate_checkpoint,
        evaluate_folders,
        format_eval_text,
        write_eval_results,
    )

    if checkpoint is not None and (pred_dir is not None or gt_dir is not None):
        raise click.UsageError("give either --checkpoint with DATASET, or --pred with --gt")
    if checkpoint is None and pred_dir is None:
        raise click.UsageError("give --checkpoint RUN/best.pt DATASET, or --pred DIR --gt DIR")
    if min_depth >= max_depth:
        raise click.BadParameter("must be below --max-depth", param_hint="--min-depth")
    output = out_dir
    median = {"auto": None, "median": True, "none": False}[scaling]
    if checkpoint is not None:
        if dataset is None:
            raise click.UsageError("--checkpoint needs the DATASET argument")
        result = evaluate_checkpoint(
            checkpoint,
            dataset,
            split=split,
            garg_crop=garg_crop,
            min_depth=min_depth,
            max_depth=max_depth,
            device=device,
            batch_size=batch_size,
            median_scaling=median,
            progress=progress_wanted(),
        )
        if output is None:
            output = Path(result.checkpoint).parent / f"eval_{split}.json"
        title = f"{result.checkpoint} on {dataset} [{split}]"
    else:
        if gt_dir is None:
            raise click.UsageError("--pred needs --gt")
        if dataset is not None:
            raise click.UsageError("DATASET is only used with --checkpoint")
        result = evaluate_folders(
            pred_dir,
            gt_dir,
            garg_crop=garg_crop,
            min_depth=min_depth,
            max_depth=max_depth,
            median_scaling=bool(median),
            progress=progress_wanted(),
        )
        title = f"{pred_dir} against {gt_dir}"
    written = write_eval_results(result, output) if output is not None else []
    if as_json:
        brief = {k: v for k, v in result.to_dict().items() if k != "per_image"}
        brief["written"] = [str(p) for p in written]
        click.echo(json.dumps(brief, indent=1))
        return
    click.echo(format_eval_text(result, title=title))
    for p in written:
        click.echo(f"written       {p}")
