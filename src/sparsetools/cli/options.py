"""Options shared by several commands, declared once here (rasterio's ``rio/options.py``).

Every option name has one declaration, hence one meaning, one type and one help text in every
command that has it (tests/test_vocabulary.py checks it). Their callbacks only parse
(:mod:`.parsing`); old spellings live on as hidden aliases (:mod:`.deprecation`).
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import click

from .deprecation import DEPRECATED, deprecated, warn_deprecated
from .parsing import (
    OldSplitFractions,
    build,
    checked,
    crop_box,
    int_list,
    named_split,
    non_negative,
    odd,
    pair,
    positive,
    size_metres,
    size_wxh,
)
from .summary import emit_summary

__all__ = [
    "DEPRECATED",
    "batch_options",
    "build",
    "calib_option",
    "checked",
    "crop_box",
    "densifier_option",
    "deprecated",
    "emit_summary",
    "image_option",
    "image_size_option",
    "int_list",
    "json_option",
    "layout_option",
    "lr_option",
    "max_depth_option",
    "min_depth_option",
    "named_split",
    "non_negative",
    "odd",
    "one_split_choice",
    "output_dir_option",
    "overwrite_option",
    "pair",
    "plot_option",
    "positive",
    "quiet_debug_options",
    "resize_option",
    "resize_to_option",
    "root_flag",
    "seed_option",
    "size_metres",
    "size_wxh",
    "verbose_option",
    "video_option",
    "warn_deprecated",
    "width_option",
]


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


def image_size_option(f=None, *, default: str | None = None, help: str | None = None):
    """``--image-size WxH``: the camera image's size in pixels."""

    def deco(fn):
        return click.option(
            "--image-size",
            callback=size_wxh,
            default=default,
            show_default=default is not None,
            metavar="WxH",
            help=help or "Image size when the calibration does not hold it (e.g. 1242x375).",
        )(fn)

    return deco(f) if f is not None else deco


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


def resize_to_option(f=None, *, help: str | None = None):
    def deco(fn):
        return click.option(
            "--resize-to", callback=size_wxh, default=None, metavar="WxH",
            help=help or "Resize every image to exactly W x H pixels (each axis scaled on its "
            "own, intrinsics too) and project at that size, e.g. 640x192 (monodepth2).",
        )(fn)  # fmt: skip

    return deco(f) if f is not None else deco


def crop_option(f=None, *, help: str | None = None):
    def deco(fn):
        return click.option(
            "--crop",
            callback=crop_box,
            metavar="WxH+LEFT+TOP",
            help=help
            or "Then crop to W x H pixels from column LEFT, row TOP, e.g. "
            "800x350+0+100 (ImageMagick's geometry).",
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


def lr_option(f=None, *, default: float = 1e-3, help: str = "Learning rate."):
    """``--lr``: the (initial) learning rate of a training command."""

    def deco(fn):
        return click.option(
            "--lr", type=click.FloatRange(min=0, min_open=True), default=default,
            show_default=True, help=help,
        )(fn)  # fmt: skip

    return deco(f) if f is not None else deco


def densifier_option(f=None, *, help: str):
    """``--densifier``: a learned densifier checkpoint (``densifier.pt`` of ``train-densifier``,
    or its run folder)."""

    def deco(fn):
        return click.option("--densifier", metavar="CHECKPOINT", default=None, help=help)(fn)

    return deco(f) if f is not None else deco


def width_option(f=None, *, default: int, help: str):
    """``--width``: channels of a network's first level."""

    def deco(fn):
        return click.option(
            "--width", type=click.IntRange(min=1), default=default, show_default=True, help=help
        )(fn)

    return deco(f) if f is not None else deco


def gt_option(f=None, *, help: str, required: bool = False, dest: str = "gt"):
    """``--gt``: ground-truth depth maps (a file, a folder tree, a dataset tree)."""

    def deco(fn):
        return click.option(
            "--gt", dest, required=required, type=click.Path(exists=True, path_type=Path),
            help=help,
        )(fn)  # fmt: skip

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


def layout_option(choices, *, default: str, help: str):
    """``--layout``: how a command lays out the files it writes (one of ``choices``)."""

    def deco(fn):
        return click.option(
            "--layout", type=click.Choice(list(choices)), default=default, show_default=True,
            help=help,
        )(fn)  # fmt: skip

    return deco


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


def _set_verbose(ctx, param, value):
    if value:
        root = ctx.find_root()
        root.ensure_object(dict)
        root.obj["verbose"] = max(int(root.obj.get("verbose", 0)), int(value))
        if not root.obj.get("quiet"):
            level = logging.INFO if root.obj["verbose"] == 1 else logging.DEBUG
            logging.getLogger().setLevel(level)
    return value


def verbose_option(f):
    """``-v/--verbose`` (a count): before the subcommand, and after it where a command has
    per-frame lines to print (``accumulate``). Read with :func:`root_flag` ``("verbose")``."""
    return click.option(
        "-v",
        "--verbose",
        count=True,
        expose_value=False,
        is_eager=True,
        callback=_set_verbose,
        help="More output: log lines on stderr (-vv: debug), and one line per frame on stdout "
        "where a command has them.",
    )(f)


def plot_option(f=None, *, help: str):
    """``--plot``: also draw the command's report as a PNG (matplotlib, the ``viz`` extra)."""

    def deco(fn):
        return click.option("--plot", is_flag=True, help=help)(fn)

    return deco(f) if f is not None else deco


def root_flag(name: str) -> bool:
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return False
    obj = ctx.find_root().obj
    return bool(obj and obj.get(name))


def split_option(dest: str = "split", *, default: str | None = None, help: str, callback=None):
    """``--split NAME``: a split by its name: one split of a dataset (``train``, ``val``,
    ``test``...) where a dataset is read; the official split (``eigen``, ``official``...) that
    makes one where a dataset is built (``callback``: :func:`.parsing.named_split`)."""

    def deco(fn):
        return click.option(
            "--split", dest, default=default, show_default=default is not None, metavar="NAME",
            callback=callback, help=help,
        )(fn)  # fmt: skip

    return deco


def one_split_choice(f):
    """``--split NAME``, ``--splits FRACTIONS`` and ``--split-file``, passed as
    ``official_split``, ``splits`` and ``split_files``, are one choice: giving two is a usage
    error. ``--split FRACTIONS`` (:class:`.parsing.OldSplitFractions`) is the 0.2 spelling of
    ``--splits``: it works, with one deprecation warning."""
    options = (
        ("--split", "official_split"),
        ("--splits", "splits"),
        ("--split-file", "split_files"),
    )

    @functools.wraps(f)
    def command(*args, **kw):
        old = kw.get("official_split")
        if isinstance(old, OldSplitFractions) and kw.get("splits") is not None:
            raise click.UsageError(f"--split {old.text} is the old spelling of --splits: give "
                                   "--splits only")  # fmt: skip
        given = [opt for opt, key in options if kw.get(key)]
        if len(given) > 1:
            raise click.UsageError(f"give one of --split, --splits and --split-file, not "
                                   f"{' and '.join(given)}")  # fmt: skip
        if isinstance(old, OldSplitFractions):
            warn_deprecated(
                f"--split {old.text} is now --splits {old.text} (--split NAME picks an official "
                "split; its fraction spelling goes in 0.4)"
            )
            kw["official_split"], kw["splits"] = None, old.value
        return f(*args, **kw)

    return command


def threads_option(f=None, *, default: int | None = 1, help: str):
    """``--threads N``: threads inside this one process (the results never depend on it)."""

    def deco(fn):
        return click.option(
            "--threads",
            type=click.IntRange(min=1),
            default=default,
            show_default=default is not None,
            help=help,
        )(fn)

    return deco(f) if f is not None else deco


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
        from ..pipeline.allocator import steady_allocator
        from ..pipeline.batch import Batch

        steady_allocator()  # the process is this command's: frames reuse what the last freed

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


# -- projection geometry -------------------------------------------------------------------------


def pixel_offset_option(f):
    """``--pixel-offset 0|-1``: monodepth2's one-pixel shift."""
    return click.option(
        "--pixel-offset",
        type=click.Choice(["0", "-1"]),
        default="0",
        show_default=True,
        help="-1 shifts pixels by one as monodepth2 does (KITTI's 1-based code).",
    )(f)


def icp_min_range_option(f):
    """``--icp-min-range``: ICP leaves out the near field (accumulate, dataset kitti-raw)."""
    return click.option(
        "--icp-min-range",
        type=float,
        default=0.0,
        show_default=True,
        callback=non_negative,
        help="ICP: leave out points nearer than this horizontal range, metres (dense traffic: 20).",
    )(f)


def filter_occluded_option(f):
    """``--filter-occluded``: drop the points the camera cannot see (ops.occlusion)."""
    return click.option(
        "--filter-occluded",
        is_flag=True,
        help="Drop see-through points: a point farther than 1.1 x the nearest point within "
        "about 0.1 m of it in the image (the LiDAR saw past a foreground edge that the camera "
        "cannot see past); accumulate: frame t's own points too, with its --occlusion-rel and "
        "--footprint-m. See docs/project.md.",
    )(f)


# -- the camera rig and nuScenes ----------------------------------------------------------------
def cameras_option(f=None, *, help: str):
    """``--cameras A,B,...``: several cameras of a rig in one dataset (one sample per frame and
    camera; docs/dataset.md, "Every camera of a rig")."""

    def deco(fn):
        return click.option("--cameras", default=None, metavar="A,B,...", help=help)(fn)

    return deco(f) if f is not None else deco


def store_points_option(f):
    """``--store-points``: each sample's scan in the camera frame (docs/dataset.md)."""
    return click.option(
        "--store-points", "store_points", is_flag=True,
        help="Store each sample's sensor points (sweeps merged) that land in the image, in the "
        "camera frame with their ring, in points/part-*.parquet (implies --store-geometry).",
    )(f)  # fmt: skip


def store_geometry_option(f):
    """``--store-geometry``: the manifest's geometry columns (docs/dataset.md, "Geometry")."""
    return click.option(
        "--store-geometry", "store_geometry", is_flag=True,
        help="Store each sample's geometry in the manifest: K, T_cam_lidar (sensor -> camera), "
        "for KITTI stereo baseline_m, for nuScenes T_ego_cam and T_world_ego.",
    )(f)  # fmt: skip


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


# -- videos ----------------------------------------------------------------------------------------


def video_option(f=None, *, help: str):
    """``--video``: the command's video mode (``synth-scene``: simulate video sequences;
    ``viz``: write MP4 videos of sequences)."""

    def deco(fn):
        return click.option("--video", is_flag=True, help=help)(fn)

    return deco(f) if f is not None else deco
