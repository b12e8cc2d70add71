"""Options shared by several commands (declared once, here) and validation callbacks.

Every option that two commands have in common is declared by a function of this module,
so it is spelt, checked and documented the same way everywhere. Callbacks validate with
:mod:`sparsetools.validate` and turn its errors into ``click.BadParameter``.
"""

from __future__ import annotations

import functools
import json
import logging
from pathlib import Path

import click

from ..errors import ParameterError

__all__ = [
    "batch_options",
    "build",
    "calib_option",
    "checked",
    "emit_summary",
    "image_option",
    "image_size_option",
    "int_list",
    "json_option",
    "max_depth_option",
    "min_depth_option",
    "output_dir_option",
    "overwrite_option",
    "pair",
    "positive",
    "quiet_debug_options",
    "resize_option",
    "seed_option",
    "size_wxh",
]


# -- callbacks: they parse text (the rules themselves are sparsetools.validate's) ------------------


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


def int_list(ctx, param, value):
    """Callback: ``5,7,9,11`` (or several values) -> a tuple of ints (None when not given)."""
    from ..validate import parse_int_list

    if value is None or value == ():
        return None
    return checked(lambda v: parse_int_list(v, param.name))(ctx, param, value)


# -- deprecated spellings (kept one release) ----------------------------------------------------------

#: Old spelling -> the option that replaces it, per command (filled by :func:`deprecated`);
#: the architecture test checks that every hidden option is one of these and that it warns.
DEPRECATED: dict[tuple[str, str], str] = {}
_DEPRECATED_KEY = "sparsetools.deprecated"


def warn_deprecated(text: str) -> None:
    """One deprecation warning line on stderr (once per message and run)."""
    ctx = click.get_current_context(silent=True)
    seen = ctx.find_root().meta.setdefault("sparsetools.warned", set()) if ctx else set()
    if text in seen:
        return
    seen.add(text)
    logging.getLogger("sparsetools.cli").warning("deprecated: %s", text)


def deprecated(
    old: str,
    new: str,
    *,
    command: str,
    dest: str,
    value=None,
    is_flag: bool = False,
    convert=None,
    metavar: str | None = None,
):
    """A hidden alias ``old`` of option ``new`` (stored in parameter ``dest``): it still works
    for one release and prints a one-line warning naming ``new``.

    The old text goes through ``new``'s own type and callback, so it is read exactly as the
    new option reads it; ``convert(text) -> text`` first rewrites it where the syntax changed
    too (``train --crop HxW`` -> ``--crop-size WxH``). ``value`` (for a flag) is the new
    option's value the old flag means (``--no-confidence`` -> ``--conf-format none``). Giving
    both spellings is a usage error.
    """
    DEPRECATED[(command, old)] = new

    def remember(ctx, param, given):
        if given is None or (is_flag and not given):
            return
        ctx.meta.setdefault(_DEPRECATED_KEY, {})[old] = given

    def deco(f):
        @functools.wraps(f)
        def command_fn(*args, **kw):
            ctx = click.get_current_context()
            store = ctx.meta.get(_DEPRECATED_KEY, {})
            if old in store:
                from click.core import ParameterSource

                if ctx.get_parameter_source(dest) not in (None, ParameterSource.DEFAULT):
                    raise click.UsageError(f"{old} is the old spelling of {new}: give {new} only")
                warn_deprecated(f"{old} is now {new} (the old spelling goes in 0.4)")
                if value is not None:
                    kw[dest] = value
                else:
                    target = next(p for p in ctx.command.params if p.name == dest)
                    text = store[old]
                    if convert is not None:
                        try:
                            text = convert(text)
                        except (TypeError, ValueError) as exc:
                            raise click.BadParameter(str(exc), param_hint=old) from None
                    try:
                        kw[dest] = target.process_value(ctx, text)
                    except click.BadParameter as exc:
                        exc.param_hint = old  # name what the user typed
                        raise
            return f(*args, **kw)

        return click.option(
            old,
            is_flag=is_flag,
            default=None,
            hidden=True,
            metavar=metavar,
            expose_value=False,
            callback=remember,
            help=f"Deprecated: use {new}.",
        )(command_fn)

    return deco


# -- shared declarations -------------------------------------------------------------------------


def output_dir_option(
    f=None, *, required: bool = True, help: str | None = None, file: bool = False
):
    """``-o/--out``: the output folder (or file, with ``file=True``)."""
    text = help or (
        "Output file (refused if it exists and was not written by this command, unless "
        "--overwrite)."
        if file
        else "Output folder (created; outputs that are up to date are skipped, other "
        "settings are refused unless --overwrite)."
    )

    def deco(fn):
        return click.option(
            "-o",
            "--out",
            "out_dir",
            required=required,
            default=None,
            type=click.Path(path_type=Path, dir_okay=not file),
            help=text,
        )(fn)

    return deco(f) if f is not None else deco


def calib_option(f=None, *, help: str | None = None, required: bool = False):
    """``--calib``: a calibration file, a KITTI raw date folder, or per-frame files."""
    text = help or (
        "KITTI object calib .txt, KITTI raw date folder, JSON calibration, or a folder of "
        "per-frame calibrations matched by frame."
    )

    def deco(fn):
        return click.option(
            "--calib",
            required=required,
            type=click.Path(exists=True, path_type=Path),
            help=text,
        )(fn)

    return deco(f) if f is not None else deco


def image_option(f=None, *, help: str | None = None, required: bool = False):
    """``--image``: an image file, or a folder of images matched by frame."""
    text = help or "Image (or folder of images matched by frame) giving the map size."

    def deco(fn):
        return click.option(
            "--image", required=required, type=click.Path(exists=True, path_type=Path), help=text
        )(fn)

    return deco(f) if f is not None else deco


def image_size_option(f):
    return click.option(
        "--image-size",
        callback=size_wxh,
        metavar="WxH",
        help="Image size when the calibration does not hold it (e.g. 1242x375).",
    )(f)


def min_depth_option(f=None, *, default: float | None = 0.1, help: str | None = None):
    def deco(fn):
        return click.option(
            "--min-depth",
            type=float,
            default=default,
            show_default=default is not None,
            callback=non_negative,
            help=help or "Drop points with depth <= this (metres).",
        )(fn)

    return deco(f) if f is not None else deco


def max_depth_option(f=None, *, default: float | None = None, help: str | None = None):
    def deco(fn):
        return click.option(
            "--max-depth",
            type=float,
            default=default,
            show_default=default is not None,
            callback=positive,
            help=help or "Drop points with depth > this (metres; default no limit).",
        )(fn)

    return deco(f) if f is not None else deco


def resize_option(f=None, *, help: str | None = None):
    def deco(fn):
        return click.option(
            "--resize",
            type=float,
            default=None,
            callback=positive,
            metavar="S",
            help=help
            or "Scale the image and intrinsics by S first (e.g. 0.5: 1600x900 -> 800x450).",
        )(fn)

    return deco(f) if f is not None else deco


def crop_option(f=None, *, help: str | None = None):
    def deco(fn):
        return click.option(
            "--crop",
            callback=crop_box,
            metavar="TOP,LEFT,H,W",
            help=help or "Then crop to H x W pixels at (TOP, LEFT), e.g. 100,0,350,800.",
        )(fn)

    return deco(f) if f is not None else deco


def format_option(choices, *, default: str, help: str):
    """``--format``: the file format of the command's main outputs."""

    def deco(fn):
        return click.option(
            "--format",
            "fmt",
            type=click.Choice(list(choices)),
            default=default,
            show_default=True,
            help=help,
        )(fn)

    return deco


def method_option(choices, *, default: str, help: str):
    """``--method``: the algorithm the command applies."""

    def deco(fn):
        return click.option(
            "--method",
            type=click.Choice(list(choices)),
            default=default,
            show_default=True,
            help=help,
        )(fn)

    return deco


def seed_option(f=None, *, default: int = 0, help: str | None = None):
    def deco(fn):
        return click.option(
            "--seed", type=int, default=default, show_default=True, help=help or "Random seed."
        )(fn)

    return deco(f) if f is not None else deco


def gt_option(f=None, *, help: str, required: bool = False):
    def deco(fn):
        return click.option(
            "--gt", required=required, type=click.Path(exists=True, path_type=Path), help=help
        )(fn)

    return deco(f) if f is not None else deco


def device_option(f):
    """``--device``: where torch runs."""
    return click.option(
        "--device", default="cpu", show_default=True, help="cpu, or cuda when available."
    )(f)


def batch_size_option(f=None, *, default: int = 8, help: str | None = None):
    def deco(fn):
        return click.option(
            "--batch-size",
            type=click.IntRange(min=1),
            default=default,
            show_default=True,
            help=help or "Samples per batch.",
        )(fn)

    return deco(f) if f is not None else deco


def json_option(f=None, *, help: str = "Print the summary as JSON on stdout."):
    def deco(fn):
        return click.option("--json", "as_json", is_flag=True, help=help)(fn)

    return deco(f) if f is not None else deco


def overwrite_option(f=None, *, help: str | None = None):
    def deco(fn):
        return click.option(
            "--overwrite",
            is_flag=True,
            help=help or "Recompute and replace outputs this command wrote before.",
        )(fn)

    return deco(f) if f is not None else deco


def _set_quiet(ctx, param, value):
    if value:
        root = ctx.find_root()
        root.ensure_object(dict)
        root.obj["quiet"] = True
        logging.getLogger().setLevel(logging.ERROR)
    return value


def _set_debug(ctx, param, value):
    if value:
        root = ctx.find_root()
        root.ensure_object(dict)
        root.obj["debug"] = True
    return value


def quiet_debug_options(f):
    """``-q/--quiet`` and ``--debug`` after the subcommand too (same as before it)."""
    f = click.option(
        "--debug",
        is_flag=True,
        expose_value=False,
        is_eager=True,
        callback=_set_debug,
        help="Show full tracebacks (also of a failed frame) instead of one-line errors.",
    )(f)
    return click.option(
        "-q",
        "--quiet",
        is_flag=True,
        expose_value=False,
        is_eager=True,
        callback=_set_quiet,
        help="Only errors on stderr; no progress bar.",
    )(f)


def root_flag(name: str) -> bool:
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return False
    obj = ctx.find_root().obj
    return bool(obj and obj.get(name))


def workers_option(f=None, *, help: str):
    """``--workers``: worker processes (the results never depend on their number)."""

    def deco(fn):
        return click.option(
            "--workers", type=click.IntRange(min=1), default=1, show_default=True, help=help
        )(fn)

    return deco(f) if f is not None else deco


def batch_options(f):
    """The batch options every batch command has, passed to the command as ``batch``.

    ``--workers``, ``--overwrite``, ``--on-error``, ``--executor``, ``--dask-scheduler``,
    ``--debug``, ``-q``: one :class:`sparsetools.pipeline.Batch`, passed as ``batch``; and
    ``--json`` (how the command prints its summary), passed as ``as_json``.
    """

    @functools.wraps(f)
    def command(*args, workers, overwrite, on_error, executor, dask_scheduler, as_json, **kw):
        from ..pipeline.batch import Batch

        batch = Batch(
            workers=workers,
            executor=executor,
            scheduler=dask_scheduler,
            overwrite=overwrite,
            on_error=on_error,
            progress=False if root_flag("quiet") else None,
            debug=root_flag("debug"),
        )
        return f(*args, batch=batch, as_json=as_json, **kw)

    decorators = [
        workers_option(
            help="Frames processed in parallel (local processes or Dask workers); capped by "
            "the frames and the CPUs available."
        ),
        overwrite_option(
            help="Recompute every frame and replace this folder's results (files the "
            "command did not write are never touched)."
        ),
        click.option(
            "--on-error",
            type=click.Choice(["stop", "skip"]),
            default="stop",
            show_default=True,
            help="Stop at the first bad frame, or skip it, list it and go on (exit 1).",
        ),
        click.option(
            "--executor",
            type=click.Choice(["local", "dask"]),
            default="local",
            show_default=True,
            help="Run frames in local processes or on a Dask cluster.",
        ),
        click.option(
            "--dask-scheduler",
            metavar="ADDRESS",
            default=None,
            help="Dask scheduler address (default: start a local cluster).",
        ),
        json_option,
        quiet_debug_options,
    ]
    return functools.reduce(lambda acc, d: d(acc), reversed(decorators), command)


# -- sensor noise and depth inputs (lowlight-synth, defocus-synth) ---------------------------------


def depth_option(f=None, *, help: str, required: bool = False):
    """``--depth``: a depth map (one image) or a folder of depth maps matched by frame."""

    def deco(fn):
        return click.option(
            "--depth", required=required, type=click.Path(exists=True, path_type=Path), help=help
        )(fn)

    return deco(f) if f is not None else deco


def noise_option(f=None, *, default: str = "eld"):
    """``--noise``: the ELD read-noise model, or none."""
    from ..ops.noise import NOISE_MODELS

    def deco(fn):
        return click.option(
            "--noise",
            type=click.Choice(NOISE_MODELS),
            default=default,
            show_default=True,
            help="Sensor noise: ELD (Tukey-lambda read noise), Gaussian read noise (ELD's "
            "separate Gaussian fit), or none.",
        )(fn)

    return deco(f) if f is not None else deco


def noise_cameras() -> tuple[str, ...]:
    """ELD noise tables shipped with the package, and ``random`` (one per image)."""
    from ..ops.noise import CAMERA_PROFILES

    return (*CAMERA_PROFILES, "random")


def noise_profile_option(f):
    """``--noise-profile``: the ELD noise table (a camera's measured noise)."""
    return click.option(
        "--noise-profile",
        type=click.Choice(noise_cameras()),
        default="SonyA7S2",
        show_default=True,
        help="ELD noise profile: the camera whose measured noise is added (random: one per image).",
    )(f)


def ratio_option(f=None, *, default: str = "2,32"):
    """``--ratio``: exposure ratio range of the noise."""

    def deco(fn):
        return click.option(
            "--ratio",
            callback=pair(low=0, strict=True),
            default=default,
            show_default=True,
            metavar="MIN,MAX",
            help="Exposure ratio ~ logU: higher = darker raw signal, more visible noise.",
        )(fn)

    return deco(f) if f is not None else deco


def color_bias_option(f):
    """``--color-bias``: add the noise table's per-channel black-level offsets."""
    return click.option(
        "--color-bias",
        is_flag=True,
        help="Add the ELD table's per-channel black-level offsets of the drawn calibration "
        "row (with the noise).",
    )(f)


def pixel_offset_option(f):
    """``--pixel-offset 0|-1``: monodepth2's one-pixel shift."""
    return click.option(
        "--pixel-offset",
        type=click.Choice(["0", "-1"]),
        default="0",
        show_default=True,
        help="-1 shifts pixels by one as monodepth2 does (KITTI's 1-based code).",
    )(f)


# -- the camera rig and nuScenes ----------------------------------------------------------------


def camera_option(f=None, *, default: str | None = None, help: str):
    """``--camera``: which camera of the rig the maps are for (a KITTI index or a nuScenes
    channel)."""

    def deco(fn):
        return click.option(
            "--camera", default=default, show_default=default is not None, help=help
        )(fn)

    return deco(f) if f is not None else deco


def sensor_option(f=None, *, default: str = "RADAR_FRONT", help: str):
    """``--sensor``: the nuScenes channel of the depth sensor (RADAR_*, LIDAR_TOP)."""

    def deco(fn):
        return click.option("--sensor", default=default, show_default=True, help=help)(fn)

    return deco(f) if f is not None else deco


# -- nuScenes -----------------------------------------------------------------------------------


def nuscenes_version_option(f):
    return click.option(
        "--nuscenes-version",
        default="v1.0-mini",
        show_default=True,
        help="nuScenes table version (folder under ROOT).",
    )(f)


def sweeps_option(f=None, *, default: int | None = None, help: str):
    def deco(fn):
        return click.option(
            "--sweeps",
            type=click.IntRange(min=1),
            default=default,
            show_default=default is not None,
            help=help,
        )(fn)

    return deco(f) if f is not None else deco


# -- output --------------------------------------------------------------------------------------


def emit_summary(summary, *, as_json: bool, title: str = "") -> None:
    """Print a run summary (a RunSummary or a dict) on stdout (key: value lines, or JSON);
    exit 1 if frames failed."""
    if hasattr(summary, "as_dict"):
        summary = summary.as_dict()
    if as_json:
        click.echo(json.dumps(summary, indent=1, default=_json_default))
    else:
        if title:
            click.echo(title)
        rows = _flatten({k: v for k, v in summary.items() if k != "failures"})
        width = max((len(k) for k, _ in rows), default=0)
        for k, v in rows:
            if isinstance(v, float):
                v = f"{v:.4g}"
            click.echo(f"{k:<{width}}  {v}")
        for fid, err in (summary.get("failures") or {}).items():
            click.echo(f"  failed {fid}: {err}")
    if summary.get("failed"):
        ctx = click.get_current_context()
        click.echo(f"Error: {summary['failed']} frame(s) failed (listed above)", err=True)
        ctx.exit(1)


def _flatten(d: dict, prefix: str = "") -> list[tuple[str, object]]:
    """Nested dicts become ``parent.child`` rows; underscores of the summary's own names read
    as spaces (nested keys are data, frame ids say: kept as they are)."""
    rows = []
    for k, v in d.items():
        key = f"{prefix}{k!s}" if prefix else str(k).replace("_", " ")
        if isinstance(v, dict):
            rows.extend(_flatten(v, key + "."))
        else:
            rows.append((key, v))
    return rows


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
