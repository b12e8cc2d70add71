"""``sparsetools eval``: depth metrics of a trained checkpoint or of any method's depth PNGs."""

from __future__ import annotations

import json
from pathlib import Path

import click
from click.core import ParameterSource

from .options import (
    batch_size_option,
    device_option,
    gt_option,
    json_option,
    max_depth_option,
    min_depth_option,
    output_dir_option,
    overwrite_option,
    plot_option,
    quiet_debug_options,
    split_option,
)
from .train import progress_wanted


def _result_files(
    output: Path, target, checkpoint: Path | None, *, overwrite: bool, plot: bool = False
) -> list:
    """The JSON and CSV results as :class:`~sparsetools.pipeline.output_file.OutputFile`, checked
    before anything is evaluated: a file that ``eval`` did not write, or that holds the results
    of another evaluation (``target``: another checkpoint, dataset, split or prediction folder),
    is refused (one line naming it and ``--overwrite``); ``eval``'s own earlier results of the
    same target are replaced, whatever protocol options made them."""
    from ..pipeline.output_file import OutputFile
    from ..train.plots import eval_plot_path
    from ..train.results import eval_result_paths

    sources = [] if checkpoint is None else [checkpoint]
    paths = list(eval_result_paths(output))
    if plot:  # --plot: the PNG beside them, under the same rule
        paths.append(eval_plot_path(paths[0]))
    files = [
        OutputFile(p, "eval", target, sources, overwrite=overwrite, noun="the results of an eval")
        for p in paths
    ]
    for f in files:
        f.up_to_date()  # raises for a file eval did not write, or wrote for another target
    return files


def _absolute(path: Path) -> str:
    return str(Path(path).resolve())


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
    help="Predicted depth maps (KITTI uint16 PNG or .npy metres): a flat folder or a sequence "
    "tree PRED/<sequence>/<frame>.png (what sparsetools commands write).",
)
@click.option(
    "--fill",
    type=click.Choice(["none", "nearest", "min-depth"]),
    default="none",
    show_default=True,
    help="--pred: how prediction holes (0, NaN: no value where the ground truth has one) are "
    "scored: none = left out of the metrics; nearest = the nearest predicted value; min-depth "
    "= as --min-depth (monodepth2's clipping). Always counted (n_holes) and named in the "
    "results.",
)
@gt_option(
    dest="gt_dir",
    help="Ground-truth depth maps: a flat folder, a sequence tree GT/<sequence>/<frame>.png, a "
    "folder written by sparsetools or a KITTI depth-completion tree; matched to --pred by "
    "(sequence, frame).",
)
@split_option(default="test", help="Split of DATASET evaluated with --checkpoint.")
@click.option("--garg-crop", is_flag=True, help="Evaluate inside the Garg crop only (KITTI Eigen).")
@min_depth_option(default=1e-3, help="Ground truth at or below this (m) is not evaluated.")
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
    "eval_<dataset folder name>_<split>.json/.csv next to it (+ _<checkpoint name> for "
    "another checkpoint than best.pt); with --pred: none. A file eval did not write, or wrote "
    "for another checkpoint, dataset, split or --pred/--gt, is refused unless --overwrite.",
)
@overwrite_option(
    help="Replace result files that eval did not write, or wrote for another evaluation."
)
@json_option(help="Print the results as JSON.")
@plot_option(help="Also write <results>.png beside the results: MAE and RMSE by ground-truth "
             "depth bin (also in the JSON as depth_bins) and histograms of per-image RMSE and "
             "AbsRel (pip install 'sparsetools[viz]').")  # fmt: skip
@quiet_debug_options
def eval_(
    dataset,
    checkpoint,
    pred_dir,
    fill,
    gt_dir,
    split,
    garg_crop,
    min_depth,
    max_depth,
    scaling,
    device,
    batch_size,
    out_dir,
    overwrite,
    as_json,
    plot,
):
    """Depth metrics per image, then averaged (AbsRel, SqRel, SqRel-KITTI, RMSE, RMSE log,
    SILog, delta1-3, MAE, iRMSE, iMAE) on pixels with min-depth < gt < max-depth.

    Camera-only self-supervised models are median-scaled per image (flagged in the output);
    for self-supervised models on sequences with true poses, also the pose ATE. --checkpoint
    needs PyTorch; --pred/--gt does not.

    --pred/--gt match frames by (sequence, frame) in flat folders, sequence trees and KITTI
    depth-completion trees: a ground-truth frame without a prediction is refused (the first
    names of both sides), predictions without ground truth are counted and named. Prediction
    holes are counted and scored as --fill says.

    \b
    Examples:
      sparsetools eval --checkpoint out/run/best.pt out/ds --split test
      sparsetools eval --pred results/depth --gt out/scene/depth_gt -o results/metrics.json
      sparsetools eval --pred results/depth --gt kitti_dc/val --fill nearest
      sparsetools eval --pred results/depth --gt out/scene/depth_gt -o results/m.json --plot
    """
    if checkpoint is not None and (pred_dir is not None or gt_dir is not None):
        raise click.UsageError("give either --checkpoint with DATASET, or --pred with --gt")
    ctx = click.get_current_context()
    fill_given = ctx.get_parameter_source("fill") not in (None, ParameterSource.DEFAULT)
    if checkpoint is not None and fill_given:
        raise click.UsageError(
            "--fill is for --pred: a network predicts every pixel (its predictions are clipped "
            "to [--min-depth, --max-depth])"
        )
    if checkpoint is None and pred_dir is None:
        raise click.UsageError("give --checkpoint RUN/best.pt DATASET, or --pred DIR --gt DIR")
    from ..errors import ParameterError
    from ..validate import check_ordered

    try:
        check_ordered(min_depth, max_depth, "min_depth", "max_depth")
    except ParameterError as exc:
        raise click.BadParameter(exc.message, param_hint=exc.option) from None
    median = {"auto": None, "median": True, "none": False}[scaling]
    bin_edges = None
    if plot:
        if checkpoint is None and out_dir is None:
            raise click.UsageError("--plot writes beside the results: give -o with --pred")
        from ..io.plots import require_matplotlib
        from ..ops.metrics import depth_bin_edges

        require_matplotlib("eval --plot")
        bin_edges = depth_bin_edges(max_depth)
    if checkpoint is not None:
        if dataset is None:
            raise click.UsageError("--checkpoint needs the DATASET argument")
        from ..train._torch_required import require_torch

        require_torch("eval --checkpoint")
        from ..train.evaluate import evaluate_checkpoint
        from ..train.results import EvalTarget, checkpoint_eval_path

        ckpt_file = checkpoint / "best.pt" if checkpoint.is_dir() else checkpoint
        output = out_dir if out_dir is not None else checkpoint_eval_path(ckpt_file, dataset, split)
        target = EvalTarget(
            checkpoint=_absolute(ckpt_file), dataset=_absolute(dataset), split=split
        )
        files = _result_files(output, target, ckpt_file, overwrite=overwrite, plot=plot)
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
            bin_edges=bin_edges,
        )
        title = f"{result.checkpoint} on {dataset} [{split}]"
    else:
        if gt_dir is None:
            raise click.UsageError("--pred needs --gt")
        if dataset is not None:
            raise click.UsageError("DATASET is only used with --checkpoint")
        from ..train.results import EvalTarget, evaluate_folders  # numpy only: no torch needed

        output = out_dir
        target = EvalTarget(pred=_absolute(pred_dir), gt=_absolute(gt_dir))
        files = (
            []
            if output is None
            else _result_files(output, target, None, overwrite=overwrite, plot=plot)
        )
        result = evaluate_folders(
            pred_dir,
            gt_dir,
            garg_crop=garg_crop,
            min_depth=min_depth,
            max_depth=max_depth,
            median_scaling=bool(median),
            fill=fill,
            progress=progress_wanted(),
            bin_edges=bin_edges,
        )
        title = f"{pred_dir} against {gt_dir}"
    from ..train.results import format_eval_text, write_eval_results

    written = write_eval_results(result, output) if output is not None else []
    if plot:
        written.append(_write_plot(result, written[0]))
    for f in files:
        f.record()
    if as_json:
        brief = {k: v for k, v in result.to_dict().items() if k != "per_image"}
        brief["written"] = [str(p) for p in written]
        click.echo(json.dumps(brief, indent=1))
        return
    click.echo(format_eval_text(result, title=title))
    for p in written:
        click.echo(f"written       {p}")


def _write_plot(result, json_path: Path) -> Path:
    """``--plot``: the result's depth bins and per-image metrics, as written to the JSON."""
    from ..io.plots import write_plot
    from ..train.plots import eval_panels, eval_plot_path

    path = eval_plot_path(json_path)
    write_plot(path, eval_panels(result.to_dict()), columns=3, panel_size=(440, 320))
    return path
