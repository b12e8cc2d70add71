"""``sparsetools eval``: depth metrics of a trained checkpoint or of any method's depth PNGs."""

from __future__ import annotations

import json
from pathlib import Path

import click

from .options import progress_enabled


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
@click.option(
    "--max-depth",
    type=click.FloatRange(min=0, min_open=True),
    default=80.0,
    show_default=True,
    help="Ground truth at or above this (m) is not evaluated.",
)
@click.option("--device", default="cpu", show_default=True, help="cpu, or cuda when available.")
@click.option("--batch-size", type=click.IntRange(min=1), default=4, show_default=True)
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    help="Results file (.json or .csv; both are written). Default with --checkpoint: "
    "eval_<split>.json/.csv next to it; with --pred: none.",
)
@click.option("--json", "as_json", is_flag=True, help="Print the results as JSON.")
def eval_(
    dataset,
    checkpoint,
    pred_dir,
    gt_dir,
    split,
    garg_crop,
    min_depth,
    max_depth,
    device,
    batch_size,
    output,
    as_json,
):
    """Depth metrics per image, then averaged (AbsRel, SqRel, SqRel-KITTI, RMSE, RMSE log,
    SILog, delta1-3, MAE, iRMSE, iMAE) on pixels with min-depth < gt < max-depth.

    \b
    Examples:
      sparsetools eval --checkpoint out/run/best.pt out/ds --split test
      sparsetools eval --pred results/depth --gt out/scene/depth_gt -o results/metrics.json
    """
    from ..ops.metrics import format_metrics_table
    from ..train.loop import evaluate_checkpoint, evaluate_folders, write_eval_results

    if checkpoint is not None and (pred_dir is not None or gt_dir is not None):
        raise click.UsageError("give either --checkpoint with DATASET, or --pred with --gt")
    if checkpoint is None and pred_dir is None:
        raise click.UsageError("give --checkpoint RUN/best.pt DATASET, or --pred DIR --gt DIR")
    if min_depth >= max_depth:
        raise click.BadParameter("must be below --max-depth", param_hint="--min-depth")
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
            progress=progress_enabled(),
        )
        if output is None:
            ckpt = Path(result["checkpoint"])
            output = ckpt.parent / f"eval_{split}.json"
        title = f"{result['checkpoint']} on {dataset} [{split}]"
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
            progress=progress_enabled(),
        )
        title = f"{pred_dir} against {gt_dir}"
    written = write_eval_results(result, output) if output is not None else []
    if as_json:
        brief = {k: v for k, v in result.items() if k != "per_image"}
        brief["written"] = [str(p) for p in written]
        click.echo(json.dumps(brief, indent=1))
        return
    click.echo(format_metrics_table(result["metrics"], title=title))
    for p in written:
        click.echo(f"written       {p}")
