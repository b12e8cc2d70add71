"""``sparsetools viz``: one picture of sparse depth over an image (several maps as panels)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import OutputError, ParameterError
from .provenance import OutputFile

__all__ = ["VizSettings", "default_labels", "render_viz"]

PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class VizSettings:
    """How the picture is drawn.

    Attributes
    ----------
    max_depth : float, metres
        Top of the colour scale, shown in red (0 m is blue, turbo colour map; ``--color-max``).
    dilate : int, pixels
        Each point is drawn as a (2 * dilate + 1)^2 square.
    horizontal : bool
        Panels left to right (default: stacked).
    labels : tuple of str, optional
        Panel labels (None: none).
    colorbar : bool
    """

    max_depth: float = field(default=80.0, metadata={"option": "--color-max"})
    dilate: int = 2
    horizontal: bool = False
    labels: tuple[str, ...] | None = None
    colorbar: bool = True


def default_labels(paths: list[Path]) -> list[str]:
    """File stems, or parent/stem when stems repeat (raw/0001.png vs jbf/0001.png)."""
    stems = [p.stem for p in paths]
    if len(set(stems)) == len(stems):
        return stems
    return [f"{p.parent.name}/{p.stem}" for p in paths]


def render_viz(
    depth: list[str | os.PathLike],
    out: str | os.PathLike,
    settings: VizSettings,
    *,
    image: str | os.PathLike | None = None,
    overwrite: bool = False,
) -> tuple[str, tuple[int, int] | None]:
    """Draw ``depth`` maps over ``image`` and write the picture (atomically).

    Returns
    -------
    status : {"written", "up to date"}
        An up-to-date picture (same inputs, same settings) is not drawn again.
    size : (width, height) or None
    """
    from ..io.dataset import read_depth_file
    from ..io.image import read_image, write_image
    from ..ops.viz import depth_panels

    out = Path(out)
    depth = [Path(p) for p in depth]
    if settings.labels is not None and len(settings.labels) != len(depth):
        raise ParameterError(
            f"{len(settings.labels)} label(s) for {len(depth)} depth map(s)", param="labels"
        )
    if out.suffix.lower() not in PICTURE_SUFFIXES:
        raise ParameterError("the picture is written as .png or .jpg", param="--out")
    sources = [*depth, *([Path(image)] if image is not None else [])]
    if out.resolve() in {p.resolve() for p in sources}:
        raise OutputError(f"output {out} would replace an input file: choose another -o")
    target = OutputFile(out, "viz", settings, sources, overwrite=overwrite, noun="a picture")
    if target.up_to_date():
        return "up to date", None
    maps = [read_depth_file(p) for p in depth]
    rgb = read_image(image) if image is not None else None
    picture = depth_panels(
        rgb,
        maps,
        labels=list(settings.labels) if settings.labels else None,
        max_depth=settings.max_depth,
        dilate=settings.dilate,
        vertical=not settings.horizontal,
        with_colorbar=settings.colorbar,
    )
    write_image(out, picture)
    target.record()
    return "written", (picture.shape[1], picture.shape[0])
