"""``sparsetools train``: the early-fusion U-Net baseline, supervised or self-supervised."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from .options import (
    batch_size_option,
    densifier_option,
    deprecated,
    device_option,
    emit_summary,
    int_list,
    json_option,
    lr_option,
    max_depth_option,
    output_dir_option,
    pair,
    quiet_debug_options,
    root_flag,
    seed_option,
    size_wxh,
    threads_option,
    width_option,
)

#: ``--input`` choices (the channels of each: docs/train.md).
INPUT_MODES = ("rgb", "rgbd", "rgbdm", "d", "rgbdc", "rgbdu")


def progress_wanted() -> bool:
    """A progress bar on stderr: when it is a terminal and ``-q`` was not given."""
    return not root_flag("quiet") and sys.stderr.isatty()


def hxw_as_wxh(text: str) -> str:
    """The pre-0.3 ``train --crop HxW`` text as ``--crop-size WxH`` text (``96x320`` -> ``320x96``)."""
    parts = str(text).lower().split("x")
    if len(parts) != 2:
        raise ValueError(
            f"expected HxW such as 96x320, got {text!r}; the new --crop-size takes WxH (320x96)"
        )
    return f"{parts[1]}x{parts[0]}"


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
    "crop_size": "crop",  # (W, H) on the command line, (H, W) in the configuration
    "seed": "seed",
    "width": "width",
    "final_layer": "final_layer",
    "loader_workers": "workers",
    "max_steps": "max_steps",
    "device": "device",
    "train_split": "train_split",
    "val_split": "val_split",
    "max_depth": "max_depth",
    "pictures": "pictures",
    "threads": "threads",
    "lidar_encoder": "lidar_encoder",
    "lidar_scales": "lidar_scales",
    "url": "url",
    "densifier": "densifier",
    "gate_alpha": "gate_alpha",
    "gate_beta": "gate_beta",
}

# CLI parameter -> the parameter of its deprecated spelling (hidden, kept for one release)
_OLD_SPELLINGS = {"crop_size": "crop", "loader_workers": "workers"}

# CLI parameter -> SelfSupSettings field (only with --self-supervised)
_SELFSUP_FIELDS = {
    "sparse_loss": "sparse_loss",
    "sparse_weight": "sparse_weight",
    "silog_lambda": "silog_lambda",
    "smoothness": "smoothness",
    "scales": "scales",
    "depth_range": "depth_range",
    "auto_mask": "auto_mask",
    "mcie": "mcie",
    "mcie_clip": "mcie_clip",
    "sbm": "sbm",
    "sbm_beta": "sbm_beta",
    "sbm_percentile": "sbm_percentile",
    "pose_width": "pose_width",
    "pose_lidar_encoder": "pose_lidar_encoder",
    "pose_translation_scale": "pose_translation_scale",
    "pose_failure_ratio": "pose_failure_ratio",
    "lidar_dropout": "lidar_dropout",
    "lidar_holdout": "lidar_holdout",
    "select_by": "select_by",
    "pbr": "pbr",
    "pbr_coordinates": "pbr_coordinates",
    "pbr_weight": "pbr_weight",
    "pbr_discriminator_weight": "pbr_discriminator_weight",
}


def selfsup_options(f):
    """The options of self-supervised training (METHODS.md section 8; docs/selfsup.md)."""
    decorators = [
        click.option(
            "--self-supervised",
            "self_supervised",
            is_flag=True,
            help="Train depth + pose networks from frame triplets (t-1, t, t+1) by view "
            "synthesis instead of on ground truth (docs/selfsup.md).",
        ),
        click.option(
            "--sparse-loss",
            type=click.Choice(["none", "l1", "silog"]),
            default="none",
            show_default=True,
            help="Self-supervised: loss on the valid sparse-depth pixels (EffisDepth); gives "
            "metric scale. none = camera only (evaluated with median scaling).",
        ),
        click.option(
            "--sparse-weight",
            type=click.FloatRange(min=0),
            default=0.1,
            show_default=True,
            help="Self-supervised: weight of the sparse loss.",
        ),
        click.option(
            "--silog-lambda",
            type=click.FloatRange(min=0, max=1),
            default=0.85,
            show_default=True,
            help="Self-supervised: lambda of the SILog sparse loss (< 1 keeps the scale).",
        ),
        click.option(
            "--smoothness",
            type=click.FloatRange(min=0),
            default=1e-3,
            show_default=True,
            help="Self-supervised: weight of the edge-aware smoothness (divided by 2^scale).",
        ),
        click.option(
            "--scales",
            type=click.IntRange(1, 4),
            default=4,
            show_default=True,
            help="Self-supervised: decoder scales in the loss.",
        ),
        click.option(
            "--depth-range",
            callback=pair(),
            default="0.1,100",
            show_default=True,
            metavar="MIN,MAX",
            help="Self-supervised: depth (m) of the sigmoid output's ends.",
        ),
        click.option(
            "--auto-mask/--no-auto-mask",
            default=True,
            show_default=True,
            help="Self-supervised: monodepth2's auto-masking of pixels the unwarped frame explains.",
        ),
        click.option(
            "--mcie/--no-mcie",
            default=False,
            show_default=True,
            help="Self-supervised, night (RNW): photometric loss on MCIE-enhanced frames, one "
            "table per triplet from the target frame.",
        ),
        click.option(
            "--mcie-clip",
            type=click.FloatRange(min=0, min_open=True),
            default=0.004,
            show_default=True,
            help="Self-supervised: MCIE clip limit (fraction of the pixels).",
        ),
        click.option(
            "--sbm/--no-sbm",
            default=False,
            show_default=True,
            help="Self-supervised, night (RNW): statistics-based mask, combined with the auto-mask.",
        ),
        click.option(
            "--sbm-beta",
            type=click.FloatRange(min=0, max=1, max_open=True),
            default=0.98,
            show_default=True,
            help="Self-supervised: EWMA factor of the SBM threshold.",
        ),
        click.option(
            "--sbm-percentile",
            type=click.FloatRange(min=0, max=100),
            default=10.0,
            show_default=True,
            help="Self-supervised: percentile of the temporal change that the SBM threshold tracks.",
        ),
        click.option(
            "--pose-width",
            type=click.IntRange(min=1),
            default=16,
            show_default=True,
            help="Self-supervised: width of the pose network's first layer.",
        ),
        click.option(
            "--pose-lidar-encoder",
            type=click.Choice(["none", "sfe", "dense"]),
            default="none",
            show_default=True,
            help="Self-supervised: LiDAR branch of the pose network too (EffisDepth's SFE in "
            "depth and pose): both frames' sparse depth, fused into its first five levels.",
        ),
        click.option(
            "--pose-translation-scale",
            type=click.FloatRange(min=0, min_open=True),
            default=None,
            help="Self-supervised: factor on the pose network's raw translation [default: "
            "0.01 (monodepth2) camera only; with --sparse-loss 0.5, the same initial flow "
            "t/z for the metric 10 m start (docs/selfsup.md)].",
        ),
        click.option(
            "--pose-failure-ratio",
            type=click.FloatRange(min=0, max=1, min_open=True),
            default=0.5,
            show_default=True,
            help="Self-supervised: flag the run as a pose failure when its last validation ATE "
            "is above this fraction of the ATE of predicting no motion (needs true poses).",
        ),
        click.option(
            "--lidar-dropout",
            type=click.FloatRange(min=0, max=1, max_open=True),
            default=0.0,
            show_default=True,
            help="Self-supervised: fraction of training batches whose LiDAR input is empty "
            "(the sparse loss keeps its points): against a LiDAR branch copying its input.",
        ),
        click.option(
            "--lidar-holdout",
            type=click.FloatRange(min=0, max=1, max_open=True),
            default=0.0,
            show_default=True,
            help="Self-supervised: fraction of each frame's points given to the sparse loss "
            "only, the rest to the LiDAR input only (disjoint sets).",
        ),
        click.option(
            "--select-by",
            type=click.Choice(["photometric", "gt"]),
            default="photometric",
            show_default=True,
            help="Self-supervised: best.pt by the validation photometric loss (reads no ground "
            "truth) or by the validation RMSE against ground truth.",
        ),
        click.option(
            "--pbr",
            metavar="REFERENCE",
            default=None,
            help="Self-supervised (RNW): priors-based regularization, a PatchGAN discriminator "
            "between the predicted depth and unpaired reference depths: the ground truth (or "
            "dense depth) of the dataset REFERENCE (docs/selfsup.md).",
        ),
        click.option(
            "--pbr-coordinates/--no-pbr-coordinates",
            default=True,
            show_default=True,
            help="Self-supervised, --pbr: the discriminator also sees the pixel coordinates "
            "(RNW's I_p).",
        ),
        click.option(
            "--pbr-weight",
            type=click.FloatRange(min=0),
            default=0.01,
            show_default=True,
            help="Self-supervised, --pbr: xi, weight of the adversarial term in the depth "
            "network's loss.",
        ),
        click.option(
            "--pbr-discriminator-weight",
            type=click.FloatRange(min=0, min_open=True),
            default=1.0,
            show_default=True,
            help="Self-supervised, --pbr: tau, weight of the discriminator's loss (its own "
            "optimizer: a learning-rate factor with SGD, nearly none with Adam).",
        ),
    ]
    for d in reversed(decorators):
        f = d(f)
    return f


@click.command("train")
@click.argument("dataset", type=click.Path(exists=True, file_okay=False, path_type=Path))
@output_dir_option(help="Run folder: metrics.csv, last.pt, best.pt, curves.png, predictions/.")
@click.option(
    "--input",
    "input_mode",
    type=click.Choice(INPUT_MODES),
    default="rgbd",
    show_default=True,
    help="Network input: rgb = camera only; rgbd = + sparse depth; rgbdm = + its validity "
    "mask; d = sparse depth alone (radar-only baseline); rgbdc = rgb + sparse depth + the "
    "confidence map of `dataset build --confidence` (JBF); rgbdu = rgb + the learned "
    "densifier's dense depth D_c and log-variance U (URL: --url, --densifier).",
)
@click.option(
    "--url",
    type=click.Choice(["residual", "gated"]),
    default=None,
    help="--input rgbdu: URL's refinement of D_c, residual D_c + R(I, U) or gated "
    "lambda(U) D_c + (1 - lambda(U)) P [default with --input rgbdu: residual] (docs/train.md).",
)
@densifier_option(
    help="--input rgbdu: the learned densifier that gives D_c and U (densifier.pt of "
    "train-densifier, or its run folder); its weights are kept in the run's checkpoints."
)
@click.option(
    "--gate-alpha",
    type=click.FloatRange(min=0, min_open=True),
    default=0.8,
    show_default=True,
    help="--url gated: alpha of the gate lambda(U) = 1 / (1 + exp(alpha (U - beta))).",
)
@click.option(
    "--gate-beta",
    type=float,
    default=0.0,
    show_default=True,
    help="--url gated: beta of the gate (U, log m^2, where it weighs D_c and P equally).",
)
@click.option(
    "--loss",
    type=click.Choice(["l1", "mse", "berhu", "silog"]),
    default="l1",
    show_default=True,
    help="Loss on valid ground-truth pixels.",
)
@click.option("--epochs", type=click.IntRange(min=1), default=20, show_default=True)
@batch_size_option(default=8)
@lr_option
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
    "--crop-size",
    callback=size_wxh,
    metavar="WxH",
    help="Bottom-centre crop of the training images to W x H pixels, e.g. 320x96 (needed "
    "when sizes differ).",
)
@deprecated("--crop", "--crop-size", command="train", dest="crop_size", convert=hxw_as_wxh)
@seed_option(help="Seed of the weights, sample order and augmentation.")
@width_option(default=32, help="Width of the first level (32 gives 32-64-128-256-512).")
@click.option(
    "--lidar-encoder",
    type=click.Choice(["none", "sfe", "dense"]),
    default="none",
    show_default=True,
    help="LiDAR branch of the depth network: sfe = EffisDepth's Sparse Feature Extractor, "
    "dense = its dense twin, its features added to each encoder level (docs/sfe.md); the "
    "U-Net then takes the image alone (--input defaults to rgb). none = early fusion only.",
)
@click.option(
    "--lidar-scales",
    default="2,4,8,16",
    show_default=True,
    callback=int_list,
    help="Encoder levels (by scale: 1 = full resolution .. 16) the LiDAR branch feeds; "
    "EffisDepth fuses at 1/2 and below (at 1 the branch can copy each LiDAR pixel to its "
    "output: docs/sfe.md).",
)
@click.option(
    "--final-layer/--no-final-layer",
    default=False,
    show_default=True,
    help="Final 3x3 adjustment layer (UltraDepth).",
)
@click.option(
    "--loader-workers",
    type=click.IntRange(min=0),
    default=0,
    show_default=True,
    help="DataLoader worker processes that read and augment samples (0: in the training "
    "process; results do not depend on it).",
)
@deprecated("--workers", "--loader-workers", command="train", dest="loader_workers")
@click.option(
    "--resume", is_flag=True, help="Continue the run in RUN_DIR exactly where it stopped."
)
@click.option(
    "--max-steps",
    type=click.IntRange(min=1),
    default=None,
    help="Stop after this many optimizer steps in total (quick runs).",
)
@device_option
@click.option("--train-split", default="train", show_default=True)
@click.option(
    "--val-split",
    default="val",
    show_default=True,
    help="Split evaluated after every epoch (best.pt = lowest RMSE on it).",
)
@max_depth_option(
    default=80.0, help="Ground truth at or beyond this (m) is neither trained on nor evaluated."
)
@click.option(
    "--pictures",
    type=click.IntRange(min=0),
    default=3,
    show_default=True,
    help="Validation samples drawn in predictions/epoch_NNN.png.",
)
@threads_option(
    default=None,
    help=(
        "torch CPU threads (default: the CPUs this process may use, at most torch's own "
        "default: the same number for the same machine, whatever its load; on a busy "
        "machine give fewer). Recorded in config.json and kept by --resume: CPU results are "
        "identical for the same count."
    ),
)
@selfsup_options
@json_option(help="Print the summary as JSON.")
@quiet_debug_options
@click.pass_context
def train(ctx, dataset, out_dir, resume, as_json, self_supervised, **options):
    """Train the early-fusion U-Net on a dataset built by `sparsetools dataset build`.

    Supervised (default): on the ground truth. --self-supervised: depth and pose networks
    from consecutive frames of the dataset's sequences (photometric loss; with --sparse-loss
    the sparse depth gives metric scale; docs/selfsup.md).

    After every epoch: validation metrics in RUN_DIR/metrics.csv, checkpoints last.pt and
    best.pt (supervised: lowest validation RMSE; self-supervised: lowest validation
    photometric loss, or RMSE with --select-by gt), curves.png and prediction pictures. The same seed
    (and --threads) gives the same metrics on CPU; --resume continues exactly, and only the
    run that RUN_DIR's config.json and metrics.csv name (every run has a run id). The same
    command again on a finished run is a no-op; other settings need another RUN_DIR.

    \b
    Examples:
      sparsetools train out/ds -o out/run_rgbd --input rgbd --epochs 20
      sparsetools train out/ds -o out/run_rgb --input rgb --width 16 --crop-size 320x96
      sparsetools train out/ds -o out/run_rgbd --resume --epochs 30
      sparsetools train out/ds -o out/run_ss --self-supervised --input rgb --width 8
      sparsetools train out/ds -o out/run_ss4 --self-supervised --sparse-loss silog
      sparsetools train out/ds -o out/sfe --self-supervised --sparse-loss silog --lidar-encoder sfe
      sparsetools train out/ds_night -o out/pbr --self-supervised --mcie --sbm --pbr out/ds_day
      sparsetools train out/ds -o out/run_sfe_sup --lidar-encoder sfe --width 16
      sparsetools train out/nus -o out/run_radar --input d
      sparsetools train out/nus_jbf -o out/run_jbf --input rgbdc
      sparsetools train out/ds -o out/url --input rgbdu --url gated --densifier out/densifier
      sparsetools eval --checkpoint out/run_rgbd/best.pt out/ds --split test
    """
    from click.core import ParameterSource

    from ..io.plots import require_matplotlib
    from ..train._torch_required import require_torch

    require_torch("train")
    require_matplotlib("train (its curves.png)")
    from ..train.config import SelfSupSettings, TrainConfig
    from ..train.loop import train as run_training

    def given(name):
        # an option given by its deprecated spelling counts as given too
        names = (name, _OLD_SPELLINGS[name]) if name in _OLD_SPELLINGS else (name,)
        return any(
            ctx.get_parameter_source(n) not in (None, ParameterSource.DEFAULT) for n in names
        )

    selfsup_values = {_SELFSUP_FIELDS[k]: options.pop(k) for k in list(_SELFSUP_FIELDS)}
    set_selfsup = [k for k in _SELFSUP_FIELDS if given(k)]
    if set_selfsup and not self_supervised and not resume:
        option = "--" + set_selfsup[0].replace("_", "-")
        raise click.UsageError(
            f"{option} is an option of self-supervised training: add --self-supervised"
        )

    if options["crop_size"] is not None:
        width, height = options["crop_size"]
        options["crop_size"] = (height, width)
    if options["lidar_encoder"] != "none" and not given("input_mode"):
        options["input_mode"] = "rgb"  # EffisDepth: the sparse depth goes to its own branch
    if options["input_mode"] == "rgbdu" and options["url"] is None:
        options["url"] = "residual"  # the survey's D_f = D_c + R(I, U)
    explicit = {_FIELDS[name] for name in _FIELDS if given(name)}
    explicit |= {f"selfsup.{_SELFSUP_FIELDS[name]}" for name in set_selfsup}
    if given("self_supervised"):
        explicit.add("self_supervised")
    config = TrainConfig(
        dataset=str(dataset),
        out_dir=str(out_dir),
        selfsup=SelfSupSettings(**selfsup_values) if self_supervised or set_selfsup else None,
        **{_FIELDS[k]: v for k, v in options.items()},
    )
    summary = run_training(
        config, resume=resume, progress=progress_wanted(), explicit=explicit
    ).to_dict()
    last = summary.pop("last") or {}
    for key in ("rmse", "abs_rel", "delta1"):
        if key in last:
            summary[f"last_{key}"] = last[key]
    emit_summary(summary, as_json=as_json, title=f"training run in {out_dir}")
