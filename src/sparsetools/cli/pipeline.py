"""``sparsetools pipeline`` and ``sparsetools demo``: run a declarative chain of commands."""

from __future__ import annotations

from pathlib import Path

import click


def _overrides(ctx, param, values):
    out = {}
    for v in values:
        key, sep, val = v.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {v!r}")
        out[key] = val
    return out


def _run(config: Path, out_dir: Path, overrides: dict, only: tuple[str, ...]) -> None:
    from ..pipeline.workflow import load_workflow, run_workflow

    wf = load_workflow(config, out_dir=out_dir, overrides=overrides)
    quiet = bool((click.get_current_context().find_root().obj or {}).get("quiet"))
    echo = (lambda s: None) if quiet else (lambda s: click.echo(s, err=True))
    results = run_workflow(wf, out_dir, only=list(only) or None, echo=echo)
    click.echo(f"{len(results)} step(s) done; report: {Path(out_dir) / 'report.md'}")


@click.command("pipeline")
@click.argument("config", type=click.Path(path_type=Path))
@click.option(
    "-o",
    "--out",
    "out_dir",
    type=click.Path(path_type=Path),
    required=True,
    help="Output folder; ${out} in the config.",
)
@click.option(
    "--set",
    "overrides",
    multiple=True,
    callback=_overrides,
    metavar="KEY=VALUE",
    help="Override a config variable (repeatable), e.g. --set data=/data/kitti.",
)
@click.option("--only", multiple=True, metavar="STEP", help="Run only the named step(s).")
def pipeline(config, out_dir, overrides, only):
    """Run the steps of a YAML/TOML CONFIG in order and write OUT/report.md.

    Each step is one sparsetools command line; ${vars} from the config's vars:
    section (and --set) are substituted, ${out} is the output folder. Steps resume,
    so a rerun after an interruption only does what is missing.

    \b
    Example:
      sparsetools pipeline sample_data/demo.yaml -o out/demo
      sparsetools pipeline my_kitti.yaml -o out/kitti --set data=/data/kitti_raw
    """
    _run(config, out_dir, overrides, only)


@click.command("demo")
@click.option(
    "-o",
    "--out",
    "out_dir",
    type=click.Path(path_type=Path),
    default=Path("out/demo"),
    show_default=True,
    help="Output folder.",
)
@click.option(
    "--config",
    type=click.Path(path_type=Path),
    default=Path("sample_data/demo.yaml"),
    show_default=True,
    help="The demo config (run from the repository root).",
)
def demo(out_dir, config):
    """Run the whole pipeline on the bundled sample data (what `make demo` does).

    \b
    Example:
      sparsetools demo -o out/demo      # then open out/demo/report.md
    """
    _run(config, out_dir, {}, ())
