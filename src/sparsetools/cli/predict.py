"""``sparsetools predict``: a trained model's depth maps over a dataset split, as depth PNGs."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from .options import (
    batch_size_option,
    device_option,
    emit_summary,
    format_option,
    json_option,
    layout_option,
    output_dir_option,
    overwrite_option,
    quiet_debug_options,
    root_flag,
    split_option,
)

log = logging.getLogger(__name__)


@click.command("predict")
@click.argument("checkpoint", type=click.Path(exists=True, path_type=Path))
@click.argument("dataset", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(
    help="Output folder (created; maps that are up to date are skipped, another checkpoint, "
    "dataset, split or layout is refused unless --overwrite)."
)
@split_option(default="test", help="Split of DATASET predicted (it needs no ground truth).")
@layout_option(
    ("tree", "kitti-dc"),
    default="tree",
    help="tree: OUT/<sequence>/<frame>.png; kitti-dc: the KITTI depth-completion submission "
    "layout, flat (<drive>_groundtruth_depth_<frame>_image_02.png for val_selection_cropped, "
    "the input's name for the test set; 1216x352).",
)
@format_option(
    ("png", "npy"),
    default="png",
    help="png: KITTI uint16 depth PNGs (depth x 256, steps of 1/256 m); npy: float32 metres "
    "(--layout tree), for relative depth that 1/256 m steps would coarsen.",
)
@device_option
@batch_size_option(default=4, help="Samples the network sees at once.")
@overwrite_option(
    help="Predict every sample again and replace this folder's maps (files predict did not "
    "write are never touched)."
)
@json_option
@quiet_debug_options
def predict(
    checkpoint, dataset, out_dir, split, layout, fmt, device, batch_size, overwrite, as_json
):
    """Run a checkpoint of `sparsetools train` (supervised or self-supervised) over one split
    of DATASET and write each sample's depth as a KITTI uint16 PNG (depth x 256), or as
    float32 metres in .npy files (--format npy).

    CHECKPOINT is best.pt / last.pt (or the run folder: its best.pt). The dataset must provide
    what the checkpoint's input mode takes (sparse depth, confidence maps). Pixels with no
    prediction (0, NaN, infinite) are written 0 and counted (holes); values a uint16 PNG
    cannot hold (>= 256 m) are clipped and counted. A camera-only self-supervised model
    predicts relative depth: score it with `eval --scaling median`. Frames run in this
    process, in order; a rerun skips maps that are up to date.

    \b
    Examples:
      sparsetools predict out/run/best.pt out/ds --split test -o out/pred
      sparsetools eval --pred out/pred --gt out/scene/depth_gt
      sparsetools predict out/run/best.pt out/dc_selection --split val_selection \\
          --layout kitti-dc -o out/submission
    """
    if layout == "kitti-dc" and fmt != "png":
        raise click.UsageError("--layout kitti-dc writes the benchmark's PNGs: --format png")
    from ..train._torch_required import require_torch

    require_torch("predict")
    from ..pipeline.batch import Batch
    from ..pipeline.core import run_job
    from ..pipeline.predict import PredictJob, PredictSample, PredictSettings
    from ..train.predict import open_predictor

    opened = open_predictor(checkpoint, dataset, split=split, device=device, batch_size=batch_size)
    samples = [
        PredictSample(i, r.sequence, r.frame, r.width, r.height, src)
        for i, (r, src) in enumerate(zip(opened.rows, opened.sources, strict=True))
    ]
    settings = PredictSettings(
        checkpoint=str(Path(opened.checkpoint).resolve()),
        dataset=str(Path(dataset).resolve()),
        split=split,
        layout=layout,
        format=fmt,
    )
    quiet = root_flag("quiet")
    batch = Batch(overwrite=overwrite, progress=False if quiet else None, debug=root_flag("debug"))
    job = PredictJob(settings, opened.predictor)
    summary = run_job(job, samples, out_dir, batch=batch, inputs=[dataset], desc="predict")
    totals = summary.as_dict()
    totals["kind"] = opened.kind
    totals["input_mode"] = opened.input_mode
    if opened.relative_depth:
        totals["scale"] = "relative (camera-only self-supervised): eval with --scaling median"
        if fmt == "png":
            log.warning("relative depth in 1/256 m steps loses precision: --format npy keeps it")
    if totals.get("holes"):
        log.warning(
            "%d pixel(s) of %d map(s) have no prediction (written 0)%s",
            totals["holes"], totals["frames_with_holes"],
            ": the KITTI devkit counts them as missing" if layout == "kitti-dc" else "",
        )  # fmt: skip
    if totals.get("clipped"):
        log.warning(
            "%d pixel(s) of %d map(s) were clipped to what a uint16 PNG holds (>= 256 m or "
            "< 1/512 m)", totals["clipped"], totals["frames_with_clipped"],
        )  # fmt: skip
    emit_summary(totals, as_json=as_json, title=f"predictions written to {out_dir}")
