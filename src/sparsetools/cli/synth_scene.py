"""``sparsetools synth-scene``: procedural street + sensor rig with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import click

from .options import emit_summary, size_wxh


@click.command("synth-scene")
@click.argument("out_dir", type=click.Path(path_type=Path))
@click.option("--seed", type=int, default=0, show_default=True, help="Scene layout and noise seed.")
@click.option(
    "--frames",
    type=click.IntRange(min=1),
    default=3,
    show_default=True,
    help="Street frames (one sequence; the ego drives ~1 m per frame).",
)
@click.option(
    "--image-size",
    callback=size_wxh,
    default="1242x375",
    show_default=True,
    metavar="WxH",
    help="Camera resolution (intrinsics scale with it).",
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
@click.option("--overwrite", is_flag=True, help="Replace existing files in OUT_DIR.")
@click.option(
    "--check",
    "check_dir",
    type=click.Path(path_type=Path, exists=True, file_okay=False),
    help="Regenerate the scene in CHECK (a synth-scene folder) from its scene.json into "
    "OUT_DIR and compare every file byte for byte (exit 1 on any difference).",
)
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON.")
def synth_scene(
    out_dir, seed, frames, image_size, underwater_frames, stem_prefix, overwrite, check_dir, as_json
):
    """Generate a synthetic KITTI-like street scene with exact ground truth.

    Writes, per frame: camera image (image_2/), 64-beam LiDAR scan in scan order
    (velodyne/, simulated laser index in velodyne_ring/), KITTI calib (calib/), dense
    ground-truth depth (depth_gt/), 5 nuScenes-format radar sweeps (radar/, calib_radar/);
    plus an underwater sequence (underwater/). Same seed, same bytes.

    \b
    Example:
      sparsetools synth-scene out/scene --seed 0 --frames 3
      sparsetools synth-scene out/small --frames 200 --image-size 320x96 --underwater-frames 0
      sparsetools synth-scene out/check --check sample_data/synthetic   # reproducible?
    """
    from ..synth import generate_scene

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

    width, height = image_size
    summary = generate_scene(
        out_dir,
        seed=seed,
        frames=frames,
        width=width,
        height=height,
        underwater_frames=underwater_frames,
        overwrite=overwrite,
        stem_prefix=stem_prefix,
    )
    emit_summary(summary, as_json=as_json, title=f"synthetic scene written to {out_dir}")
