"""``sparsetools train``: the early-fusion U-Net depth-completion baseline."""

from __future__ import annotations

from pathlib import Path

import click

from .options import emit_summary, progress_enabled


def crop_hxw(ctx, param, value):
    """Parse ``HxW`` (e.g. 256x1216) into (H, W)."""
    if value is None:
        return None
    try:
        h, w = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"expected HxW such as 256x1216, got {value!r}") from None
    if h <= 0 or w <= 0:
        raise click.BadParameter(f"height and width must be positive, got {value!r}")
    return h, w


# CLI parameter -> TrainConfig field
_FIELDS = {
    "input_mode": "input_mode",
    "loss": "loss",
    "epochs": "epochs",
    "batch_size": "batch_size",
    "lr": "lr",
    "optimizer": "optimizer",
    "lr_schedule": "lr_schedule",
    "lr_step": "lr_step",
    "lr_gamma": "lr_gamma",
    "crop": "crop",
    "seed": "seed",
    "width": "width",
    "final_layer": "final_layer",
    "workers": "workers",
    "max_steps": "max_steps",
    "device": "device",
    "train_split": "train_split",
    "val_split": "val_split",
    "max_depth": "max_depth",
    "pictures": "pictures",
    "threads": "threads",
}


@click.command("train")
@click.argument("dataset", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option(
    "-o",
    "--out",
    "run_dir",
    required=True,
    type=click.Path(path_type=Path),
    help="Run folder: metrics.csv, last.pt, best.pt, curves.png, predictions/.",
)
@click.option(
    "--input",
    "input_mode",
    type=click.Choice(["rgb", "rgbd", "rgbdm"]),
    default="rgbd",
    show_default=True,
    help="Camera only, camera + sparse depth, or + its validity mask.",
)
@click.option(
    "--loss",
    type=click.Choice(["l1", "mse", "berhu", "silog"]),
    default="l1",
    show_default=True,
    help="Loss on valid ground-truth pixels.",
)
@click.option("--epochs", type=click.IntRange(min=1), default=20, show_default=True)
@click.option("--batch-size", type=click.IntRange(min=1), default=8, show_default=True)
@click.option(
    "--lr",
    type=click.FloatRange(min=0, min_open=True),
    default=1e-3,
    show_default=True,
    help="Learning rate.",
)
@click.option("--optimizer", type=click.Choice(["adam", "sgd"]), default="adam", show_default=True)
@click.option(
    "--lr-schedule",
    type=click.Choice(["constant", "step", "cosine"]),
    default="constant",
    show_default=True,
    help="Learning rate per epoch: constant; x GAMMA every --lr-step epochs; cosine down to "
    "1/100 over --epochs.",
)
@click.option(
    "--lr-step",
    type=click.IntRange(min=1),
    default=5,
    show_default=True,
    help="Epochs between decays of --lr-schedule step.",
)
@click.option(
    "--lr-gamma",
    type=click.FloatRange(min=0, max=1, min_open=True),
    default=0.5,
    show_default=True,
    help="Decay factor of --lr-schedule step.",
)
@click.option(
    "--crop",
    callback=crop_hxw,
    metavar="HxW",
    help="Bottom-centre crop of training images (needed when sizes differ).",
)
@click.option(
    "--seed",
    type=int,
    default=0,
    show_default=True,
    help="Seed of the weights, sample order and augmentation.",
)
@click.option(
    "--width",
    type=click.IntRange(min=1),
    default=32,
    show_default=True,
    help="Width of the first level (32 gives 32-64-128-256-512).",
)
@click.option(
    "--final-layer/--no-final-layer",
    default=False,
    show_default=True,
    help="Final 3x3 adjustment layer (UltraDepth).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="DataLoader worker processes (results do not depend on it).",
)
@click.option(
    "--resume", is_flag=True, help="Continue the run in RUN_DIR exactly where it stopped."
)
@click.option(
    "--max-steps",
    type=click.IntRange(min=1),
    default=None,
    help="Stop after this many optimizer steps in total (quick runs).",
)
@click.option("--device", default="cpu", show_default=True, help="cpu, or cuda when available.")
@click.option("--train-split", default="train", show_default=True)
@click.option(
    "--val-split",
    default="val",
    show_default=True,
    help="Split evaluated after every epoch (best.pt = lowest RMSE on it).",
)
@click.option(
    "--max-depth",
    type=click.FloatRange(min=0, min_open=True),
    default=80.0,
    show_default=True,
    help="Ground truth beyond this (m) is not evaluated.",
)
@click.option(
    "--pictures",
    type=click.IntRange(min=0),
    default=3,
    show_default=True,
    help="Validation samples drawn in predictions/epoch_NNN.png.",
)
@click.option(
    "--threads",
    type=click.IntRange(min=1),
    default=None,
    help="torch CPU threads (default: the cores available).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
@click.pass_context
def train(ctx, dataset, run_dir, resume, as_json, **options):
    """Train the early-fusion U-Net on a dataset built by `sparsetools dataset build`.

    After every epoch: validation metrics in RUN_DIR/metrics.csv, checkpoints last.pt and
    best.pt (lowest validation RMSE), curves.png and prediction pictures. The same seed
    gives the same metrics on CPU; --resume continues exactly.

    \b
    Examples:
      sparsetools train out/ds -o out/run_rgbd --input rgbd --epochs 20
      sparsetools train out/ds -o out/run_rgb --input rgb --width 16 --crop 96x320
      sparsetools train out/ds -o out/run_rgbd --resume --epochs 30
      sparsetools eval --checkpoint out/run_rgbd/best.pt out/ds --split test
    """
    from ..train.loop import TrainConfig
    from ..train.loop import train as run_training

    explicit = {
        _FIELDS[name]
        for name in _FIELDS
        if ctx.get_parameter_source(name) is not click.core.ParameterSource.DEFAULT
    }
    config = TrainConfig(
        dataset=str(dataset), out_dir=str(run_dir), **{_FIELDS[k]: v for k, v in options.items()}
    )
    summary = run_training(config, resume=resume, progress=progress_enabled(), explicit=explicit)
    last = summary.pop("last") or {}
    for key in ("rmse", "abs_rel", "delta1"):
        if key in last:
            summary[f"last_{key}"] = last[key]
    emit_summary(summary, as_json=as_json, title=f"training run in {run_dir}")
