"""``sparsetools synth-scene``: procedural street + sensor rig with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import click
from click.core import ParameterSource

from .options import (
    emit_summary,
    image_size_option,
    json_option,
    output_dir_option,
    overwrite_option,
    quiet_debug_options,
    seed_option,
    video_option,
    warn_deprecated,
    workers_option,
)

#: Defaults of --frames and --image-size in video mode (when not given).
VIDEO_FRAMES, VIDEO_SIZE = 30, (416, 128)
_VIDEO_ONLY = ("sequences", "static", "antialias", "image_noise", "workers")
_SINGLE_ONLY = ("underwater_frames", "stem_prefix")


@click.command("synth-scene")
@click.argument("legacy_out", required=False, metavar="", type=click.Path(path_type=Path))
@output_dir_option(
    required=False,
    help="Output folder (a folder this command made with the same options is kept as it is; "
    "other options are refused unless --overwrite).",
)
@seed_option(help="Scene layout and noise seed.")
@click.option(
    "--frames",
    type=click.IntRange(min=1),
    default=3,
    show_default=True,
    help="Street frames (one sequence; the ego drives ~1 m per frame). Video mode: frames "
    "per sequence at 10 Hz (default 30).",
)
@image_size_option(
    default="1242x375",
    help="Camera resolution (intrinsics scale with it). Video mode default 416x128.",
)
@click.option(
    "--underwater-frames",
    type=click.IntRange(min=0),
    default=40,
    show_default=True,
    help="Frames of the underwater sequence (0 = none).",
)
@click.option(
    "--stem-prefix",
    default="",
    metavar="TEXT",
    help="Prefix of the frame file names (s1_ gives s1_000000.png): lets several "
    "sequences share one dataset without name clashes.",
)
@video_option(
    help="Video mode: --sequences street videos with exact camera/LiDAR poses, moving "
    "cars and people, a moving-object mask (docs/synth-scene.md)."
)
@click.option(
    "--sequences",
    type=click.IntRange(min=1),
    default=1,
    show_default=True,
    help="Video mode: sequences, each its own street and drive (seq_0000, ...).",
)
@click.option("--static", is_flag=True, help="Video mode: no moving cars, nobody walks.")
@click.option(
    "--antialias",
    type=click.IntRange(1, 4),
    default=2,
    show_default=True,
    help="Video mode: colour samples per pixel along each axis.",
)
@click.option(
    "--image-noise",
    type=click.FloatRange(min=0.0),
    default=0.0,
    show_default=True,
    metavar="SIGMA",
    help="Video mode: Gaussian image noise, grey levels.",
)
@workers_option(help="Video mode: frames simulated in parallel (same bytes for any number).")
@overwrite_option(help="Regenerate the folder even when it holds a scene made otherwise.")
@click.option(
    "--check",
    "check_dir",
    type=click.Path(path_type=Path, exists=True, file_okay=False),
    help="Regenerate the scene in CHECK (a synth-scene folder) from its scene.json into "
    "OUT_DIR and compare every file byte for byte (exit 1 on any difference).",
)
@json_option
@quiet_debug_options
def synth_scene(
    legacy_out,
    out_dir,
    seed,
    frames,
    image_size,
    underwater_frames,
    stem_prefix,
    video,
    sequences,
    static,
    antialias,
    image_noise,
    workers,
    overwrite,
    check_dir,
    as_json,
):
    """Generate a synthetic KITTI-like street scene with exact ground truth.

    Writes, per frame: camera image (image_2/), 64-beam LiDAR scan in scan order
    (velodyne/, simulated laser index in velodyne_ring/), KITTI calib (calib/), dense
    ground-truth depth (depth_gt/), 5 nuScenes-format radar sweeps (radar/, calib_radar/);
    plus an underwater sequence (underwater/). Same seed, same bytes.

    With --video: street videos at 10 Hz, one folder per sequence (image_2/, velodyne/,
    depth_gt/, moving_mask/, calib/, poses.txt, poses_velodyne.txt, poses/, times.txt,
    scene.json).

    \b
    Example:
      sparsetools synth-scene -o out/scene --seed 0 --frames 3
      sparsetools synth-scene -o out/small --frames 200 --image-size 320x96 --underwater-frames 0
      sparsetools synth-scene -o out/check --check sample_data/synthetic   # reproducible?
      sparsetools synth-scene -o out/video --video --sequences 4 --frames 30 --image-size 416x128
    """
    from ..pipeline.synth_scene import run_synth_scene

    ctx = click.get_current_context()
    if legacy_out is not None:
        if out_dir is not None:
            raise click.UsageError("give the output folder once, as -o OUT")
        warn_deprecated("synth-scene OUT_DIR is now synth-scene -o OUT_DIR (the old form goes "
                        "in 0.4)")  # fmt: skip
        out_dir = legacy_out
    if out_dir is None:
        raise click.UsageError("Missing option '-o' / '--out'.")

    def given(name: str) -> bool:
        return ctx.get_parameter_source(name) not in (ParameterSource.DEFAULT, None)

    if video:
        wrong = [n for n in _SINGLE_ONLY if given(n)]
    else:
        wrong = [n for n in _VIDEO_ONLY if given(n)]
    if wrong:
        flag = "--" + wrong[0].replace("_", "-")
        raise click.UsageError(
            f"{flag} does not apply {'to --video' if video else 'without --video'}"
        )

    if check_dir is not None:
        from ..errors import FormatError
        from ..synth.verify import regenerate_and_compare

        result = regenerate_and_compare(check_dir, out_dir)
        summary = {
            "files": result["files"],
            "identical": result["identical"],
            "missing": len(result["missing"]),
            "extra": len(result["extra"]),
            "different": len(result["different"]),
        }
        emit_summary(summary, as_json=as_json, title=f"regenerated {check_dir} into {out_dir}")
        bad = result["missing"] + result["different"]
        if bad:
            raise FormatError(
                f"{len(bad)} file(s) differ from {check_dir} (first: {bad[0]}): the generator "
                "changed, regenerate with `make sample-data`"
            )
        return

    if video:
        from ..pipeline.synth_scene import run_synth_video

        summary = run_synth_video(
            out_dir,
            seed=seed,
            sequences=sequences,
            n_frames=frames if given("frames") else VIDEO_FRAMES,
            image_size=image_size if given("image_size") else VIDEO_SIZE,
            static=static,
            antialias=antialias,
            image_noise=image_noise,
            workers=workers,
            overwrite=overwrite,
        )
        summary.pop("lidar_points", None)  # per frame: too long for the terminal summary
        emit_summary(summary, as_json=as_json, title=f"synthetic videos in {out_dir}")
        return

    width, height = image_size
    summary = run_synth_scene(
        out_dir,
        seed=seed,
        frames=frames,
        width=width,
        height=height,
        underwater_frames=underwater_frames,
        overwrite=overwrite,
        stem_prefix=stem_prefix,
    )
    emit_summary(summary, as_json=as_json, title=f"synthetic scene in {out_dir}")
