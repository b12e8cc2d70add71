"""``sparsetools viz``: sparse depth coloured over an image; several maps side by side."""

from __future__ import annotations

from pathlib import Path

import click


def _labels_callback(ctx, param, value):
    if value is None:
        return None
    return [s.strip() for s in value.split(",")]


def _default_labels(paths: list[Path]) -> list[str]:
    """File stems, or parent/stem when stems repeat (raw/0001.png vs jbf/0001.png)."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [f"{p.parent.name}/{p.stem}" for p in paths]


@click.command("viz")
@click.argument(
    "depth", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path)
)
@click.option(
    "--image",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Camera image under the points (default: black).",
)
@click.option(
    "-o",
    "--out",
    "out_path",
    required=True,
    type=click.Path(dir_okay=False, path_type=Path),
    help="Output picture (.png or .jpg).",
)
@click.option(
    "--max-depth",
    type=click.FloatRange(min=0, min_open=True),
    default=80.0,
    show_default=True,
    help="Depth (m) shown in red; 0 m is blue (turbo).",
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
@click.option("--overwrite", is_flag=True, help="Replace OUT if it exists.")
def viz(
    depth,
    image,
    out_path,
    max_depth,
    dilate,
    side_by_side,
    horizontal,
    labels,
    no_colorbar,
    overwrite,
):
    """Colour sparse depth blue (0 m) to red (--max-depth) over a camera image.

    DEPTH is a KITTI uint16 depth PNG or a .npy of metres; with several DEPTH the panels are
    stacked (labelled) over the same image, e.g. raw vs expanded, or 1/4/16 beams.

    \b
    Examples:
      sparsetools viz out/depth/000000.png --image out/scene/image_2/000000.png -o v.png
      sparsetools viz --side-by-side out/b1/000000.png out/b4/000000.png out/b16/000000.png \\
          --image out/scene/image_2/000000.png --labels "1 beam,4 beams,16 beams" -o beams.png
    """
    from ..io.dataset import read_depth_file
    from ..io.image import read_image, write_image
    from ..ops.viz import depth_panels

    if labels is not None and labels != [""] and len(labels) != len(depth):
        raise click.BadParameter(
            f"{len(labels)} label(s) for {len(depth)} depth map(s)", param_hint="--labels"
        )
    if out_path.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise click.BadParameter("output must be .png or .jpg", param_hint="--out")
    inputs = {p.resolve() for p in (*depth, *([image] if image is not None else []))}
    if out_path.resolve() in inputs:
        from ..errors import OutputError

        raise OutputError(f"output {out_path} would replace an input file: choose another -o")
    if labels is None:
        labels = _default_labels(list(depth)) if len(depth) > 1 else None
    elif labels == [""]:
        labels = None
    maps = [read_depth_file(p) for p in depth]
    rgb = read_image(image) if image is not None else None
    picture = depth_panels(
        rgb,
        maps,
        labels=labels,
        max_depth=max_depth,
        dilate=dilate,
        vertical=not horizontal,
        with_colorbar=not no_colorbar,
    )
    write_image(out_path, picture, overwrite=overwrite)
    click.echo(f"wrote {out_path} ({picture.shape[1]}x{picture.shape[0]})")
