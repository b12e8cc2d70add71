"""``sparsetools train-densifier``: the learned densifier (SpaDe-style, with uncertainty)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from .options import (
    batch_size_option,
    build,
    device_option,
    emit_summary,
    image_size_option,
    int_list,
    json_option,
    lr_option,
    max_depth_option,
    output_dir_option,
    overwrite_option,
    quiet_debug_options,
    root_flag,
    seed_option,
    size_wxh,
    threads_option,
    width_option,
)


@click.command("train-densifier")
@click.argument(
    "scenes",
    nargs=-1,
    metavar="[SCENE...]",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
)
@output_dir_option(help="Run folder: densifier.pt, metrics.csv, config.json (refused when it "
                   "holds anything, unless --overwrite).")  # fmt: skip
@click.option(
    "--sim-frames",
    type=click.IntRange(min=1),
    default=12,
    show_default=True,
    help="Without SCENE: street frames simulated in memory (7 m apart; about 0.5 s each at "
    "1242x375).",
)
@image_size_option(default="1242x375", help="Without SCENE: size of the simulated frames "
                   "(train at the size you will densify).")  # fmt: skip
@click.option(
    "--beam-counts",
    default="64,16,4",
    show_default=True,
    callback=int_list,
    metavar="N[,N...]",
    help="Beam counts the 64-beam scans are thinned to for the inputs (64; 8, 16, 32: "
    "every 64/N-th laser; 1-4: the lasers nearest the horizon).",
)
@click.option("--steps", type=click.IntRange(min=1), default=300, show_default=True,
              help="Optimizer steps (about 0.17 s each on one core at the defaults).")  # fmt: skip
@batch_size_option(default=4)
@click.option(
    "--tile-size",
    default="256x128",
    show_default=True,
    callback=size_wxh,
    metavar="WxH",
    help="Random window of a frame per sample (clipped to the frame).",
)
@lr_option(default=2e-3, help="Initial learning rate (cosine decay to 0 over --steps).")
@width_option(default=8, help="Channels of the full-resolution level (8 gives 8-16-32-32-64; "
              "0.22 s per 1242x375 frame on one core).")  # fmt: skip
@click.option(
    "--nll-weight",
    type=click.FloatRange(min=0),
    default=1.0,
    show_default=True,
    help="Weight of the heteroscedastic term 0.5 exp(-U) (D_c - D)^2 + 0.5 U beside the L1 "
    "term (0: no uncertainty is learned).",
)
@click.option(
    "--corrupt",
    type=click.FloatRange(0, 1),
    default=0.0,
    show_default=True,
    metavar="P",
    help="Probability per sample of a rectangle whose measurements are made wrong (each "
    "depth times exp(N(0, 0.5^2))) while the target stays the truth: U learns to rise on "
    "inconsistent measurements (outliers), at the cost of a larger U on clean input "
    "(docs/densify.md).",
)
@max_depth_option(default=80.0, help="Truth beyond this (m) is not trained on.")
@seed_option(help="Seed of the simulated street, the weights and the samples.")
@threads_option(
    default=None,
    help="torch CPU threads (default: the CPUs this process may use). The same seed and "
    "thread count give the same weights on CPU.",
)
@device_option
@overwrite_option(help="Train into a folder that holds files (densifier.pt, metrics.csv and "
                  "config.json are replaced; nothing else is removed).")  # fmt: skip
@json_option
@quiet_debug_options
def train_densifier(scenes, out_dir, sim_frames, image_size, beam_counts, steps, batch_size,
                    tile_size, lr, width, nll_weight, corrupt, max_depth, seed, threads,
                    device, overwrite, as_json):  # fmt: skip
    """Train the learned densifier (SpaDe-style: coarse dense depth D_c and log-variance U).

    Trains on the street frames of SCENE folders written by `sparsetools synth-scene` (their
    exact depth is the target), or, without SCENE, on --sim-frames street frames simulated in
    memory. Each sample is a random window of a frame, its scan thinned to one of
    --beam-counts and projected; the loss is L1 + --nll-weight x the Gaussian
    heteroscedastic term (docs/densify.md). Writes OUT/densifier.pt, OUT/metrics.csv and
    OUT/config.json; use the checkpoint with `densify --method learned --densifier`. The same
    seed and --threads give the same weights on CPU.

    \b
    Examples:
      sparsetools train-densifier -o out/densifier --threads 1        # about a minute
      sparsetools densify out/depth -o out/dense_learned --method learned \\
          --densifier out/densifier/densifier.pt --uncertainty
      sparsetools synth-scene -o out/street --frames 40 --underwater-frames 0
      sparsetools train-densifier out/street -o out/densifier_40 --steps 2000
    """
    from click.core import ParameterSource

    ctx = click.get_current_context()
    given = [n for n in ("sim_frames", "image_size")
             if ctx.get_parameter_source(n) not in (None, ParameterSource.DEFAULT)]  # fmt: skip
    if scenes and given:
        flag = "--" + given[0].replace("_", "-")
        raise click.UsageError(f"{flag} sets the simulated frames: it does not apply with SCENE")
    from ..train._torch_required import require_torch

    require_torch("train-densifier")
    from ..train.densifier_train import DensifierTrainConfig, train_densifier

    config = build(
        DensifierTrainConfig,
        scenes=tuple(str(s) for s in scenes),
        sim_frames=sim_frames,
        image_size=image_size,
        beam_counts=beam_counts,
        steps=steps,
        batch_size=batch_size,
        tile_size=tile_size,
        lr=lr,
        width=width,
        max_depth=max_depth,
        nll_weight=nll_weight,
        corrupt=corrupt,
        seed=seed,
        threads=threads,
        device=device,
    )
    progress = not root_flag("quiet") and sys.stderr.isatty()
    tree = None
    if not config.scenes:
        # simulated frames are a function of the settings: a finished run with the same ones is
        # up to date (a rerun does nothing), one made with others is refused naming the option
        from ..pipeline.output_file import OutputTree
        from ..train.densifier_train import RUN_FILES, recorded_run

        tree = OutputTree(out_dir, "train-densifier", config.to_dict(), noun="a densifier run",
                          overwrite=overwrite)  # fmt: skip
        done = recorded_run(out_dir) if tree.up_to_date() else None
        if done is not None:
            emit_summary(done.to_dict(), as_json=as_json,
                         title=f"densifier in {out_dir} is up to date")  # fmt: skip
            return
    run = train_densifier(config, out_dir, overwrite=overwrite, progress=progress)
    if tree is not None:
        tree.record([Path(out_dir) / name for name in RUN_FILES])
    emit_summary(run.to_dict(), as_json=as_json, title=f"densifier trained in {out_dir}")
