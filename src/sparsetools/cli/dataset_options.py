"""Options of the ``dataset`` commands: splits (fractions, lists, official names), stores and
roots, generation parameters. Each declared once (the shared ones are in :mod:`.options`)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from ..errors import ParameterError
from .options import (
    checked,
    named_split,
    one_split_choice,
    split_option,
)
from .parsing import named_paths

__all__ = [
    "SPLIT_NAMES",
    "params_callback",
    "root_option",
    "sequence_callback",
    "split_file_callback",
    "split_file_option",
    "splits_callback",
    "splits_option",
    "store_option",
]


def splits_callback(ctx, param, value):
    if value is None or value == "tree":
        return value
    from ..pipeline.dataset import parse_split_fractions

    return checked(parse_split_fractions)(ctx, param, value)


#: The official splits each route takes (``--split NAME``), as the help names them; the
#: catalogue is :mod:`sparsetools.pipeline.dataset.official_splits` (a test keeps them equal).
SPLIT_NAMES = {
    "kitti": ("eigen", "eigen_full", "eigen_benchmark", "odom"),
    "nuscenes": ("official", "mini"),
}
_SPLIT_HELP = {
    "kitti": "eigen (Eigen-Zhou train/val, Eigen test), eigen_full, eigen_benchmark, odom",
    "nuscenes": "official (train/val/test scenes), mini (mini_train/mini_val)",
}


def splits_option(*, dataset: str, tree: bool = False):
    """The split of a built dataset, one choice of three: ``--split NAME`` (an official split
    of ``dataset``: ``kitti`` or ``nuscenes``), ``--splits`` (fractions over sequences;
    ``tree``: or the input tree's split) and ``--split-file`` (lists), passed as
    ``official_split``, ``splits`` and ``split_files``. ``--split FRACTIONS``, 0.2's spelling
    of ``--splits``, still works with a warning."""
    metavar = "TRAIN,VAL,TEST|tree" if tree else "TRAIN,VAL,TEST"
    text = "Split fractions over sequences [default: 0.8,0.1,0.1]; or name=fraction,..."
    if tree:
        text += "; or 'tree': the split of a KITTI depth-completion tree (train / val)."
    unit = "scene" if dataset == "nuscenes" else "frame"
    official = (f"An official split list set shipped with sparsetools: {_SPLIT_HELP[dataset]}; "
                f"each {unit} goes to the split whose list names it, unlisted ones are left "
                "out (docs/dataset.md).")  # fmt: skip

    def deco(f):
        f = one_split_choice(f)
        f = click.option(
            "--splits", "splits", callback=splits_callback, metavar=metavar, help=text
        )(f)
        return split_option("official_split", callback=named_split(dataset), help=official)(f)

    return deco


def sequence_callback(ctx, param, value):
    from ..pipeline.dataset import sequence_resolver

    checked(lambda v: sequence_resolver(v, "sequence"))(ctx, param, value)
    return value


def split_file_callback(ctx, param, value):
    out = []
    for item in value or ():
        name, sep, path = item.partition("=")
        if sep and not Path(item).exists():
            if not name or not Path(path).is_file():
                raise click.BadParameter(f"expected NAME=PATH with an existing file, got {item!r}")
            out.append((name, path))
        elif ":" in item and not Path(item).exists():  # a shipped list: eigen:test
            from ..pipeline.dataset.official_splits import shipped_split_file

            try:
                part, path = shipped_split_file(item)
            except ParameterError as exc:
                raise click.BadParameter(str(exc)) from None
            out.append((part, str(path)))
        else:
            if not Path(item).is_file():
                raise click.BadParameter(f"no such split file: {item}")
            out.append(item)
    return tuple(out)


def params_callback(ctx, param, value):
    if value is None:
        return None
    text = value
    if not value.lstrip().startswith("{"):
        p = Path(value)
        if not p.is_file():
            raise click.BadParameter("expected a JSON object or a JSON file")
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise click.BadParameter(f"cannot read {value} as UTF-8 JSON ({exc})") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as exc:
        raise click.BadParameter(f"not valid JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise click.BadParameter("expected the generation parameters as a JSON object")
    return obj


def store_option(f):
    """``--store``: how a dataset build stores the camera images."""
    return click.option(
        "--store", type=click.Choice(["copy", "link", "reference"]), default="copy",
        show_default=True, help="Camera images: copy them in, link (reflinks where the file "
        "system has them, else copies) or reference them in place (docs/dataset.md).",
    )(f)  # fmt: skip


def root_option(f):
    """``--root NAME=PATH``, repeatable: where a root of referenced files is now."""
    return click.option(
        "--root", "roots", multiple=True, callback=named_paths, metavar="NAME=PATH",
        help="Where a root of referenced images is now (default: where the build found it).",
    )(f)  # fmt: skip


def split_file_option(*, help: str):
    """``--split-file [NAME=]FILE``, repeatable: the frames of one split by list (or a
    shipped list, ``NAME:SPLIT`` such as ``eigen:test``)."""
    return click.option(
        "--split-file", "split_files", multiple=True, callback=split_file_callback,
        metavar="[NAME=]FILE|LIST:SPLIT", help=help + " A shipped list is named LIST:SPLIT "
        "(eigen:test, eigen_benchmark:test, official:val).",
    )  # fmt: skip
