"""The ``sparsetools`` command group.

Subcommands are imported only when invoked (``--help`` stays fast). Library errors
(:class:`sparsetools.errors.SparsetoolsError`) become one line on stderr and exit code 1;
usage errors are click's (exit code 2); ``--debug`` shows tracebacks.
"""

from __future__ import annotations

import importlib
import logging
import sys

import click

from .._version import __version__
from ..errors import FrameError, UsageError
from .options import quiet_debug_options, verbose_option

# command name -> "module:function" under sparsetools.cli
COMMANDS = {
    "synth-scene": "synth_scene:synth_scene",
    "project": "project:project",
    "beams": "beams:beams",
    "jbf-expand": "jbf_expand:jbf_expand",
    "lowlight-synth": "lowlight_synth:lowlight_synth",
    "equalize": "equalize:equalize",
    "defocus-synth": "defocus_synth:defocus_synth",
    "dark-channel": "dark_channel:dark_channel",
    "underwater": "underwater:underwater",
    "densify": "densify:densify",
    "accumulate": "accumulate:accumulate",
    "dataset": "dataset:dataset",
    "viz": "viz:viz",
    "stats": "stats:stats",
    "train": "train:train",
    "train-densifier": "train_densifier:train_densifier",
    "eval": "eval:eval_",
    "predict": "predict:predict",
    "pipeline": "pipeline:pipeline",
    "demo": "pipeline:demo",
}


class LazyGroup(click.Group):
    """A click group whose subcommands are imported on first use."""

    def list_commands(self, ctx):
        return [name for name in COMMANDS if self.get_command(ctx, name) is not None]

    def get_command(self, ctx, name):
        target = COMMANDS.get(name)
        if target is None:
            return None
        module, attr = target.split(":")
        name = f"sparsetools.cli.{module}"
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # command not built yet in this checkout
                return None
            raise
        return getattr(mod, attr)

    def invoke(self, ctx):
        from ..errors import SparsetoolsError

        try:
            return super().invoke(ctx)
        except SparsetoolsError as exc:
            debug = bool(ctx.params.get("debug") or (ctx.obj or {}).get("debug"))
            text = str(exc)
            if debug:
                # The frame's own traceback (from a worker) follows the first line.
                click.echo(f"Error: {text}", err=True)
                import traceback

                traceback.print_exception(exc, file=sys.stderr)
                ctx.exit(1)
            # One line, whatever the message holds (third-party texts can span lines).
            first = text.split("\n", 1)[0] if isinstance(exc, FrameError) else text
            click.echo(f"Error: {' '.join(first.split())}", err=True)
            ctx.exit(2 if isinstance(exc, UsageError) else 1)
        except KeyboardInterrupt:
            click.echo("Interrupted: completed outputs are kept; rerun to resume.", err=True)
            ctx.exit(130)
        except MemoryError:
            click.echo("Error: out of memory (try fewer --workers or smaller inputs)", err=True)
            ctx.exit(1)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name="sparsetools")
@verbose_option
@quiet_debug_options
@click.pass_context
def cli(ctx):
    """Turn camera + sparse depth sensor data into depth-estimation datasets.

    \b
    Typical flow:
      sparsetools synth-scene -o out/scene --frames 3          # sample data with ground truth
      sparsetools project out/scene/velodyne --calib out/scene/calib -o out/depth
      sparsetools beams out/scene/velodyne --n 4 -o out/beams4
    Every command has --help with a worked example.
    """
    ctx.ensure_object(dict)
    quiet = ctx.obj.get("quiet", False)  # set by -q (before or after the subcommand)
    verbose = ctx.obj.get("verbose", 0)  # set by -v (before the subcommand; accumulate after)
    level = (
        logging.ERROR if quiet else (logging.WARNING, logging.INFO, logging.DEBUG)[min(verbose, 2)]
    )
    logging.basicConfig(
        level=level, format="%(levelname)s: %(message)s", stream=sys.stderr, force=True
    )
    ctx.obj.setdefault("quiet", False)
    ctx.obj.setdefault("debug", False)


def main(argv=None):
    """Console-script entry point."""
    cli.main(args=argv, prog_name="sparsetools")


if __name__ == "__main__":  # pragma: no cover
    main()
