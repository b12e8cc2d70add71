"""``sparsetools pipeline`` and ``sparsetools demo``: run a declarative chain of commands."""

from __future__ import annotations

from pathlib import Path

import click

from .options import output_dir_option, overwrite_option, quiet_debug_options


def _overrides(ctx, param, values):
    out = {}
    for v in values:
        key, sep, val = v.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {v!r}")
        out[key] = val
    return out


def run_command(args: list[str]) -> tuple[int, str, str]:
    """Run one sparsetools command line in this process: (exit code, stdout, stderr)."""
    import contextlib
    import io

    from ..errors import SparsetoolsError
    from .main import cli

    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            # With standalone_mode=False click returns the code of ctx.exit(n) instead of exiting.
            ret = cli.main(args=["-q", *args], prog_name="sparsetools", standalone_mode=False)
            code = ret if isinstance(ret, int) else 0
        except SystemExit as exc:  # ctx.exit() inside commands
            code = int(exc.code or 0) if not isinstance(exc.code, str) else 1
        except SparsetoolsError as exc:
            err.write(f"Error: {exc}\n")
            code = 1
        except Exception as exc:  # click usage errors and anything unexpected
            msg = exc.format_message() if hasattr(exc, "format_message") else str(exc)
            err.write(f"Error: {msg}\n")
            code = getattr(exc, "exit_code", 1) or 1
    return code, out.getvalue(), err.getvalue()


def _run(config: Path, out_dir: Path, overrides: dict, only: tuple[str, ...],
         overwrite: bool = False) -> None:  # fmt: skip
    from ..pipeline.workflow import load_workflow, run_workflow

    wf = load_workflow(config, out_dir=out_dir, overrides=overrides)
    quiet = bool((click.get_current_context().find_root().obj or {}).get("quiet"))
    echo = (lambda s: None) if quiet else (lambda s: click.echo(s, err=True))
    results = run_workflow(wf, out_dir, run_command=run_command, only=list(only) or None,
                           echo=echo, overwrite=overwrite)  # fmt: skip
    click.echo(f"{len(results)} step(s) done; report: {Path(out_dir) / 'report.md'}")


@click.command("pipeline")
@click.argument("config", type=click.Path(path_type=Path))
@output_dir_option(help="Output folder; ${out} in the config.")
@click.option(
    "--set",
    "overrides",
    multiple=True,
    callback=_overrides,
    metavar="KEY=VALUE",
    help="Override a config variable (repeatable), e.g. --set data=/data/kitti.",
)
@click.option("--only", multiple=True, metavar="STEP", help="Run only the named step(s).")
@overwrite_option(help="Replace OUT/report.md and OUT/steps.json even when the pipeline did not "
                  "write them (the steps' own outputs follow each command's rule).")  # fmt: skip
@quiet_debug_options
def pipeline(config, out_dir, overrides, only, overwrite):
    """Run the steps of a YAML/TOML CONFIG in order and write OUT/report.md.

    Each step is one sparsetools command line; ${vars} from the config's vars:
    section (and --set) are substituted, ${out} is the output folder. Steps resume,
    so a rerun after an interruption only does what is missing.

    \b
    Example:
      sparsetools pipeline sample_data/demo.yaml -o out/demo
      sparsetools pipeline my_kitti.yaml -o out/kitti --set data=/data/kitti_raw
    """
    _run(config, out_dir, overrides, only, overwrite)


@click.command("demo")
@output_dir_option(required=False, help="Output folder [default: out/demo].")
@click.option(
    "--config",
    type=click.Path(path_type=Path),
    default=Path("sample_data/demo.yaml"),
    show_default=True,
    help="The demo config (run from the repository root).",
)
@quiet_debug_options
def demo(out_dir, config):
    """Run the whole pipeline on the bundled sample data (what `make demo` does).

    A second run reuses every output that is up to date and rewrites the report.

    \b
    Example:
      sparsetools demo -o out/demo      # then open out/demo/report.md
    """
    _run(config, out_dir or Path("out/demo"), {}, ())
