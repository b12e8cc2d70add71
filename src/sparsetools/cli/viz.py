"""``sparsetools viz``: sparse depth coloured over an image; several maps side by side."""

from __future__ import annotations

from pathlib import Path

import click

from .options import (
    deprecated,
    image_option,
    output_dir_option,
    overwrite_option,
    positive,
    quiet_debug_options,
)


def _labels_callback(ctx, param, value):
    if value is None:
        return None
    return [s.strip() for s in value.split(",")]


@click.command("viz")
@click.argument(
    "depth", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path)
)
@image_option(help="Camera image under the points (default: black).")
@output_dir_option(file=True, help="Output picture (.png or .jpg); an up-to-date picture is kept.")
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
@overwrite_option(help="Replace OUT even if it was not written by viz.")
@deprecated("--max-depth", "--color-max", command="viz", dest="color_max")
@quiet_debug_options
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
    overwrite,
):
    """Colour sparse depth blue (0 m) to red (--color-max) over a camera image.

    DEPTH is a KITTI uint16 depth PNG or a .npy of metres; with several DEPTH the panels are
    stacked (labelled) over the same image, e.g. raw vs expanded, or 1/4/16 beams.

    \b
    Examples:
      sparsetools viz out/depth/000000.png --image out/scene/image_2/000000.png -o v.png
      sparsetools viz --side-by-side out/b1/000000.png out/b4/000000.png out/b16/000000.png \\
          --image out/scene/image_2/000000.png --labels "1 beam,4 beams,16 beams" -o beams.png
    """
    from ..pipeline.viz import VizSettings, default_labels, render_viz

    if out_dir.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise click.BadParameter("the picture is written as .png or .jpg", param_hint="--out")
    if labels is not None and labels != [""] and len(labels) != len(depth):
        raise click.BadParameter(
            f"{len(labels)} label(s) for {len(depth)} depth map(s)", param_hint="--labels"
        )
    if labels is None:
        labels = default_labels(list(depth)) if len(depth) > 1 else None
    elif labels == [""]:
        labels = None
    settings = VizSettings(
        max_depth=color_max,
        dilate=dilate,
        horizontal=horizontal,
        labels=None if labels is None else tuple(labels),
        colorbar=not no_colorbar,
    )
    status, size = render_viz(list(depth), out_dir, settings, image=image, overwrite=overwrite)
    if status == "written":
        click.echo(f"wrote {out_dir} ({size[0]}x{size[1]})")
    else:
        click.echo(f"{out_dir} is up to date")
