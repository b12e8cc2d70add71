"""``sparsetools beams``: 64-beam LiDAR to 1/2/3/4/8/16/32 beams (or a ring table)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import click

from .options import (
    batch_options,
    calib_option,
    checked,
    emit_summary,
    format_option,
    image_option,
    image_size_option,
    output_dir_option,
    plot_option,
    size_wxh,
)

_INTS = re.compile(r"^\d+(,\d+)*,?$")


class _GreedyIntsOption(click.Option):
    """An option that also takes the integers following it: ``--line-spec 5 7 9 11``.

    (Pseudo-LiDAR++'s argparse spelling; ``--line-spec 5,7,9,11`` works too.)
    """

    def add_to_parser(self, parser, ctx):
        super().add_to_parser(parser, ctx)
        for name in self.opts:
            opt = getattr(parser, "_long_opt", {}).get(name) or getattr(
                parser, "_short_opt", {}
            ).get(name)
            if opt is None or not hasattr(opt, "process"):
                continue  # unknown click internals: only the comma form works then
            original = opt.process

            def process(value, state, _original=original):
                values = [value]
                while getattr(state, "rargs", None) and _INTS.match(state.rargs[0]):
                    values.append(state.rargs.pop(0))
                _original(" ".join(values), state)

            opt.process = process


def _n_values(ctx, param, value):
    """``--n 4`` or ``--n 1,2,4,16``: beam counts >= 1, each once."""
    from ..validate import parse_int_list

    values = checked(lambda v: parse_int_list(v, "n", low=1, unique=True))(ctx, param, value)
    if value is not None and not values:
        raise click.BadParameter("no beam count given")
    return values or ()


def _non_negative_ints(ctx, param, value):
    """Ring or bin numbers >= 0, each once."""
    from ..validate import parse_int_list

    if value is None or value == ():
        return None
    return checked(lambda v: parse_int_list(v, param.name, low=0, unique=True))(ctx, param, value)


@click.command("beams")
@click.argument("clouds", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--n",
    "n",
    callback=_n_values,
    metavar="N[,N...]",
    help="Beams to keep: one N (OUT/<stem>.bin) or several, e.g. 1,2,4,16 "
    "(OUT/n<N>/<stem>.bin each).",
)
@click.option(
    "--select",
    type=click.Choice(["horizon", "uniform", "pl++"]),
    default=None,
    help="horizon: the N lasers nearest -0.2/-1.0/-1.8/-2.6 deg (default for N <= 4); "
    "uniform: every (L/N)-th laser (default above 4); pl++: Pseudo-LiDAR++ "
    "sparsify.py emulation (elevation bins; needs --calib).",
)
@click.option(
    "--rings",
    callback=_non_negative_ints,
    metavar="R,R,...",
    help="Keep these rings (0 = highest laser) instead of a selection.",
)
@click.option(
    "--ring-method",
    type=click.Choice(["scan-order", "elevation", "column"]),
    default=None,
    help="How rings are recovered [default: column for nuScenes .pcd.bin, else "
    "scan-order, falling back to elevation with a warning].",
)
@click.option(
    "--lasers",
    "n_lasers",
    type=click.IntRange(1, 256),
    default=None,
    help="Lasers of the sensor [default: 32 with --ring-method column, else 64].",
)
@click.option(
    "--profile",
    default="auto",
    show_default=True,
    metavar="NAME|JSON|none",
    help="Sensor profile (laser elevations and cones): auto = hdl64e-kitti for "
    "64-laser clouds without a ring column.",
)
@click.option(
    "--line-spec",
    cls=_GreedyIntsOption,
    callback=_non_negative_ints,
    metavar="B B ...",
    help="pl++ elevation bins to keep, e.g. 5 7 9 11 (implies pl++).",
)
@click.option(
    "--pl-grid",
    default="1024x64",
    show_default=True,
    callback=size_wxh,
    metavar="WxH",
    help="pl++ grid: W azimuth bins over 90 deg, H elevation bins of 0.4*64/H deg.",
)
@calib_option(
    help="Calibration (file, KITTI raw folder, or per-frame folder matched by frame): "
    "reports the projected map's density per N; needed by pl++."
)
@image_size_option
@image_option
@format_option(
    ["bin", "npy", "pcd"], default="bin", help="Output format (bin keeps the input's float32 rows)."
)
@click.option(
    "--far-range",
    type=click.FloatRange(min=0),
    default=20.0,
    show_default=True,
    help="Points beyond this horizontal range (m) give a laser's elevation.",
)
@click.option(
    "--report",
    is_flag=True,
    help="Only print each cloud's ring table (ring, points, median elevation).",
)
@plot_option(help="With --report: draw the ring tables as OUT/ring_report.png (points and median "
             "elevations per ring, one line per cloud) and print one line per cloud "
             "(pip install 'sparsetools[viz]').")  # fmt: skip
@output_dir_option(required=False)
@batch_options
def beams(
    clouds,
    n,
    select,
    rings,
    ring_method,
    n_lasers,
    profile,
    line_spec,
    pl_grid,
    calib,
    image_size,
    image,
    fmt,
    far_range,
    report,
    plot,
    out_dir,
    batch,
    as_json,
):
    """Keep 1-32 beams of 64-beam LiDAR scans (all columns of the kept points).

    CLOUD may be files or folders (.bin KITTI, .pcd.bin nuScenes, .npy, .pcd), KITTI raw
    drives or date folders, or a KITTI object root. Rings are recovered from the scan order
    (ring 0 = highest laser); the same lasers are kept on every frame. Writes
    OUT/<sequence>/<frame>.bin (OUT/n<N>/<sequence>/<frame>.bin for several N); a flat
    folder of clouds has no <sequence>/ level.

    \b
    Examples:
      sparsetools beams kitti/velodyne --n 4 -o out/beams4
      sparsetools beams kitti/velodyne --n 1,2,4,16 --calib kitti/calib \\
          --image kitti/image_2 -o out/beams
      sparsetools beams kitti/velodyne --select pl++ --line-spec 5 7 9 11 \\
          --calib kitti/calib --image kitti/image_2 -o out/plpp4
      sparsetools beams raw/2011_09_26/2011_09_26_drive_0001_sync --n 4 -o out/b4
      sparsetools beams --report kitti/velodyne/000001.bin
      sparsetools beams --report --plot kitti/velodyne -o out/rings
    """
    from ..io.sources import cloud_frames
    from ..pipeline import run_job
    from ..pipeline.beams import BeamsJob, BeamsSettings, ring_report

    pl_width, pl_height = pl_grid
    if plot and not report:
        raise click.UsageError("--plot goes with --report")
    if report:
        if plot:
            if out_dir is None:
                raise click.UsageError("--report --plot writes OUT/ring_report.png: give -o OUT")
            from ..io.plots import require_matplotlib

            require_matplotlib("beams --report --plot")
        settings = BeamsSettings(n=(1,), ring_method=ring_method, n_lasers=n_lasers,
                                 profile=profile, far_range=far_range)  # fmt: skip
        reports = ring_report(list(clouds), settings)
        written = _plot_report(reports, out_dir, overwrite=batch.overwrite) if plot else None
        if as_json:
            click.echo(json.dumps([r.to_dict() for r in reports], indent=1))
        else:
            for r in reports:  # with --plot, the tables are in the picture (and in --json)
                click.echo(r.format() if written is None else r.format().splitlines()[0])
            if written is not None:
                click.echo(f"plot: {written}")
        return
    if out_dir is None:
        raise click.UsageError("Missing option '-o' / '--out' (or use --report).")
    if not n and rings is None and line_spec is None:
        raise click.UsageError("give the number of beams (--n), --rings or --line-spec")
    if (image_size is not None or image is not None) and calib is None:
        raise click.UsageError("--image-size / --image go with --calib")
    settings = BeamsSettings(
        n=n,
        select=select,
        rings=rings,
        ring_method=ring_method,
        n_lasers=n_lasers,
        profile=profile,
        line_spec=line_spec,
        pl_width=pl_width,
        pl_height=pl_height,
        fmt=fmt,
        far_range=far_range,
        image_size=image_size,
    )
    # A KITTI raw / object tree brings its calibration: the density is reported then too.
    frames = cloud_frames(list(clouds), calib=calib, image=image)
    summary = run_job(BeamsJob(settings), frames, out_dir, batch=batch,
                      inputs=[*clouds, calib, image])  # fmt: skip
    emit_summary(summary, as_json=as_json, title=f"beams written to {out_dir}")


def _plot_report(reports, out_dir: Path, *, overwrite: bool) -> Path:
    """``--report --plot``: the ring tables, as printed with ``--json``, drawn as one PNG."""
    from ..pipeline.plots import RING_REPORT_PLOT, ring_report_panels, write_command_plot

    panels = ring_report_panels([r.to_dict() for r in reports])
    return write_command_plot(out_dir / RING_REPORT_PLOT, panels,
                              command="beams --report --plot", overwrite=overwrite)  # fmt: skip
