"""``sparsetools viz``: sparse depth coloured over an image; several maps side by side; over
many frames, contact sheets (``--sheet``) and MP4 videos (``--video``)."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    batch_options,
    build,
    checked,
    deprecated,
    emit_summary,
    image_option,
    output_dir_option,
    positive,
    size_wxh,
    split_option,
    video_option,
)


def _labels_callback(ctx, param, value):
    if value is None:
        return None
    return [s.strip() for s in value.split(",")]


def _frame_range(ctx, param, value):
    from ..validate import parse_frame_range

    return checked(lambda v: (parse_frame_range(v, "--frame-range"), v)[1])(ctx, param, value)


@click.command("viz")
@click.argument("depth", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@image_option(
    help="Camera image under the points (default: black); a folder of images matched by frame "
    "for folder inputs."
)
@output_dir_option(
    help="Output picture (.png or .jpg) of one frame, or the folder of the --sheet pages or "
    "--video files; up-to-date outputs are kept, other settings refused unless --overwrite."
)
@click.option(
    "--color-max",
    type=float,
    default=80.0,
    show_default=True,
    callback=positive,
    metavar="METRES",
    help="Top of the colour scale: this depth (m) is red, 0 m blue (turbo); farther points "
    "are drawn red too.",
)
@click.option(
    "--dilate",
    type=click.IntRange(min=0, max=50),
    default=2,
    show_default=True,
    help="Draw each point as a (2*DILATE+1)^2 square.",
)
@click.option(
    "--side-by-side",
    is_flag=True,
    help="Compare several depth maps over the same image (implied by several DEPTH).",
)
@click.option("--horizontal", is_flag=True, help="Lay panels out left to right (default: stacked).")
@click.option(
    "--labels",
    callback=_labels_callback,
    metavar="A,B,...",
    help="Panel labels (default: file names); '' for none.",
)
@click.option("--no-colorbar", is_flag=True, help="Leave out the colour bar.")
@click.option(
    "--sheet",
    is_flag=True,
    help="Contact sheets: pages of --grid tiles (depth over image, frame key on each), "
    "OUT/sheet_0001.png, ...",
)
@video_option(help="One MP4 video per sequence (OUT/<sequence>.mp4), depth over image.")
@click.option(
    "--grid",
    callback=size_wxh,
    metavar="WxH",
    help="--sheet: tiles across x down per page [default: 4x3].",
)
@click.option(
    "--tile-width",
    type=click.IntRange(min=32),
    metavar="PIXELS",
    help="--sheet: width of one tile [default: 320]; its height follows the frames' shape.",
)
@click.option(
    "--fps",
    type=float,
    callback=positive,
    help="--video: frames per second [default: 10].",
)
@click.option(
    "--frame-range",
    default="",
    callback=_frame_range,
    metavar="FROM:TO[:STEP]",
    help="Only these frames of a folder or dataset: positions in the sorted frame keys, "
    "Python slice syntax (0:100, ::10, -50:).",
)
@split_option(help="The split of a dataset DEPTH (default: every sample).")
@deprecated("--max-depth", "--color-max", command="viz", dest="color_max")
@batch_options
def viz(
    depth,
    image,
    out_dir,
    color_max,
    dilate,
    side_by_side,
    horizontal,
    labels,
    no_colorbar,
    sheet,
    video,
    grid,
    tile_width,
    fps,
    frame_range,
    split,
    batch,
    as_json,
):
    """Colour sparse depth blue (0 m) to red (--color-max) over a camera image.

    DEPTH is a KITTI uint16 depth PNG or a .npy of metres; with several DEPTH the panels are
    stacked (labelled) over the same image, e.g. raw vs expanded, or 1/4/16 beams.

    DEPTH may also be a folder (a folder tree OUT/<sequence>/<frame>.png as sparsetools
    commands write, a KITTI depth-completion tree) or ONE dataset folder (dataset build;
    --split picks a split): several folders are matched by (sequence, frame), --image is a
    folder matched the same way. Over many frames, --sheet writes contact sheets and --video
    one MP4 per sequence into the folder -o; a folder holding one frame without either gives
    the one picture.

    \b
    Examples:
      sparsetools viz out/depth/000000.png --image out/scene/image_2/000000.png -o v.png
      sparsetools viz --side-by-side out/b1/000000.png out/b4/000000.png out/b16/000000.png \\
          --image out/scene/image_2/000000.png --labels "1 beam,4 beams,16 beams" -o beams.png
      sparsetools viz out/n64 --image sample_data/synthetic/image_2 --sheet --grid 3x2 -o sheets
      sparsetools viz out/radar out/jbf --image scene/image_2 --video --fps 10 -o videos
      sparsetools viz out/dataset --split val --sheet --frame-range ::10 -o val_sheets
    """
    from ..errors import UsageError
    from ..pipeline import run_job
    from ..pipeline.viz import (
        ManyVizSettings,
        SheetJob,
        VideoJob,
        VizSettings,
        default_labels,
        render_viz,
        viz_frames,
    )

    if sheet and video:
        raise UsageError("--sheet and --video: choose one")
    if labels is not None and labels != [""] and len(labels) != len(depth) and len(depth) > 1:
        raise click.BadParameter(
            f"{len(labels)} label(s) for {len(depth)} depth map(s)", param_hint="--labels"
        )
    if sheet or video:
        mode = "sheet" if sheet else "video"
        settings = build(
            ManyVizSettings,
            mode=mode, max_depth=color_max, dilate=dilate, horizontal=horizontal,
            colorbar=not no_colorbar, grid=grid, tile_width=tile_width, fps=fps,
            frame_range=frame_range, split=split,
        )  # fmt: skip
        if out_dir.suffix.lower() in (".png", ".jpg", ".jpeg", ".mp4"):
            raise UsageError(f"--{mode} writes a folder of files: give -o a folder name")
        frames, dataset, panels = viz_frames(
            depth, image=image, split=split, frame_range=frame_range
        )
        panels = panels or tuple(default_labels(list(depth)))
        if labels == [""]:
            labels = None
        elif labels is None:
            labels = panels if len(panels) > 1 else None
        job_type = SheetJob if sheet else VideoJob
        job = job_type(
            settings=settings, panels=tuple(panels),
            labels=None if labels is None else tuple(labels),
            dataset=None if dataset is None else str(dataset),
        )  # fmt: skip
        summary = run_job(job, frames, out_dir, batch=batch, inputs=[*depth, image])
        what = "contact sheets" if sheet else "videos"
        emit_summary(summary, as_json=as_json, title=f"{what} written to {out_dir}")
        return
    for name, value in (("--grid", grid), ("--tile-width", tile_width), ("--fps", fps),
                        ("--split", split)):  # fmt: skip
        if value is not None:
            raise UsageError(f"{name} is an option of --sheet or --video")
    if out_dir.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise click.BadParameter("the picture is written as .png or .jpg", param_hint="--out")
    if labels is not None and labels != [""] and len(labels) != len(depth):
        raise click.BadParameter(
            f"{len(labels)} label(s) for {len(depth)} depth map(s)", param_hint="--labels"
        )
    if all(p.is_file() for p in depth) and not frame_range:
        files, image_file = list(depth), image
    else:  # folders: exactly one frame (possibly picked by --frame-range) makes the picture
        frames, dataset, _ = viz_frames(depth, image=image, frame_range=frame_range)
        if dataset is not None or len(frames) != 1:
            n = "a dataset" if dataset is not None else f"{len(frames)} frames"
            raise UsageError(
                f"DEPTH holds {n}: give --sheet or --video (or --frame-range to pick one frame)"
            )
        files, image_file = list(frames[0].depths), frames[0].image
    if labels is None:
        labels = default_labels(files) if len(files) > 1 else None
    elif labels == [""]:
        labels = None
    settings = VizSettings(
        max_depth=color_max,
        dilate=dilate,
        horizontal=horizontal,
        labels=None if labels is None else tuple(labels),
        colorbar=not no_colorbar,
    )
    status, size = render_viz(files, out_dir, settings, image=image_file,
                              overwrite=batch.overwrite)  # fmt: skip
    if as_json:
        import json

        click.echo(json.dumps({"status": status, "output": str(out_dir),
                               "size": None if size is None else list(size)}))  # fmt: skip
    elif status == "written":
        click.echo(f"wrote {out_dir} ({size[0]}x{size[1]})")
    else:
        click.echo(f"{out_dir} is up to date")
