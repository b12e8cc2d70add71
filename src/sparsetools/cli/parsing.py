"""Option callbacks: they parse text; the rules themselves are :mod:`sparsetools.validate`'s.

A callback turns the option's text into a value (``WxH`` -> ``(W, H)``) and a
:class:`~sparsetools.errors.ParameterError` into ``click.BadParameter`` (exit code 2, naming
the option); :func:`build` does the same for a settings record made from options.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import click

from ..errors import ParameterError
from .deprecation import warn_deprecated

__all__ = [
    "build",
    "checked",
    "crop_box",
    "int_list",
    "named_split",
    "non_negative",
    "odd",
    "pair",
    "positive",
    "size_metres",
    "size_wxh",
]


def checked(fn):
    """Adapt ``fn(value) -> value`` raising ParameterError into a click callback."""

    def callback(ctx, param, value):
        if value is None:
            return None
        try:
            return fn(value)
        except ParameterError as exc:  # click names the option itself
            raise click.BadParameter(exc.message) from None

    return callback


def build(cls, /, **values):
    """``cls(**values)``: a settings record made from options, which validates itself; a
    value it refuses is a usage error naming the option (exit code 2), as click's own are."""
    try:
        return cls(**values)
    except ParameterError as exc:
        raise click.BadParameter(exc.message, param_hint=exc.option) from None


def positive(ctx, param, value):
    """Callback: a finite number > 0 (None passes)."""
    from ..validate import check_positive

    return checked(lambda v: check_positive(v, param.name))(ctx, param, value)


def non_negative(ctx, param, value):
    """Callback: a finite number >= 0 (None passes)."""
    from ..validate import check_non_negative

    return checked(lambda v: check_non_negative(v, param.name))(ctx, param, value)


def odd(ctx, param, value):
    """Callback: an odd integer >= 1 (a window centred on its pixel or frame)."""
    from ..validate import check_odd

    return checked(lambda v: check_odd(v, param.name))(ctx, param, value)


def size_wxh(ctx, param, value):
    """Callback: ``WxH`` (e.g. 1242x375) -> (W, H) pixels."""
    from ..validate import parse_size

    return checked(lambda v: parse_size(v, param.name if param else "size"))(ctx, param, value)


def size_metres(ctx, param, value):
    """Callback: ``WxH`` in metres (e.g. 2.35x2.35) -> (W, H) floats."""
    from ..validate import parse_size

    return checked(lambda v: parse_size(v, param.name, integer=False))(ctx, param, value)


def crop_box(ctx, param, value):
    """Callback: ``WxH+LEFT+TOP`` -> ``(top, left, height, width)``; the pre-0.3 text
    ``TOP,LEFT,H,W`` is still read, with a deprecation warning."""
    from ..validate import format_crop, is_legacy_crop, parse_crop

    box = checked(lambda v: parse_crop(v, param.name))(ctx, param, value)
    if box is not None and is_legacy_crop(value):
        warn_deprecated(
            f"--crop {value} (TOP,LEFT,H,W) is the old syntax: write --crop {format_crop(box)} "
            "(WxH+LEFT+TOP)"
        )
    return box


def pair(*, integer: bool = False, single: bool = False, low: float | None = None,
         strict: bool = False):  # fmt: skip
    """Callback factory: ``A,B`` (and ``V`` for ``(V, V)`` when ``single``) -> an ordered pair
    of finite numbers, ``A`` above ``low`` (``>`` when ``strict``)."""
    from ..validate import parse_pair

    def parse(ctx, param, value):
        def one(v):
            return parse_pair(v, param.name, integer=integer, single=single, low=low, strict=strict)

        return checked(one)(ctx, param, value)

    return parse


def named_paths(ctx, param, value):
    """Repeated ``NAME=PATH`` -> {name: Path} (``--root kitti=/data/kitti``)."""
    from pathlib import Path

    out = {}
    for item in value or ():
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise click.BadParameter(f"expected NAME=PATH, got {item!r}")
        if name in out:
            raise click.BadParameter(f"{name!r} given twice")
        out[name] = Path(path)
    return out


def int_list(ctx, param, value):
    """Callback: ``5,7,9,11`` (or several values) -> a tuple of ints (None when not given)."""
    from ..validate import parse_int_list

    if value is None or value == ():
        return None
    return checked(lambda v: parse_int_list(v, param.name))(ctx, param, value)


class OldSplitFractions(NamedTuple):
    """``--split 0.8,0.1,0.1``: sparsetools 0.2's spelling of ``--splits`` (``value``: what
    ``--splits`` reads from ``text``); the command warns and uses it as ``--splits``."""

    value: Any
    text: str


def named_split(dataset: str, *, fractions: str = "splits"):
    """Callback factory: ``--split NAME``, a split shipped for ``dataset`` (``kitti``,
    ``nuscenes``). A text with ``,`` or ``=`` (``0.8,0.1,0.1``, ``train=0.9,val=0.1``), or one
    that the command's option ``fractions`` reads otherwise (``tree``), is 0.2's spelling of
    that option: read as it reads it, returned as :class:`OldSplitFractions`. Any other text is a
    usage error listing the names."""

    def parse(ctx, param, value):
        from ..pipeline.dataset.official_splits import official_split_names

        names = official_split_names(dataset)
        if value is None or value in names:
            return value
        target = next((p for p in ctx.command.params if p.name == fractions), None)
        if target is not None:
            try:
                return OldSplitFractions(target.process_value(ctx, value), value)
            except click.BadParameter as exc:
                if "," in value or "=" in value:  # fractions, badly written
                    exc.param_hint = "'--split'"
                    raise
        raise click.BadParameter(
            f"unknown split {value!r}: the official splits are {', '.join(names)} "
            "(split fractions go in --splits)"
        )

    return parse
