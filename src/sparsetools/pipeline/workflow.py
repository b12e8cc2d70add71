"""Declarative multi-step runs: ``sparsetools pipeline CONFIG.yaml`` and ``make demo``.

A config lists steps; each step is one ``sparsetools`` command line (as in a shell) run
in-process, its stdout captured into ``OUT/report.md`` together with the pictures it names
(``images:``, shown) and the other files it wants linked (``links:``: an HTML page, a video)::

    name: my run
    vars:                          # ${name} is replaced everywhere; ${out} is the output folder
      data: /data/kitti/2011_09_26/2011_09_26_drive_0001_sync
    steps:
      - name: project LiDAR
        run: project ${data}/velodyne_points/data --calib ${data}/.. -o ${out}/depth
        images: [${out}/depth_viz.png]
      - name: beams
        run: beams ${data}/velodyne_points/data --n 4 -o ${out}/beams4

YAML (``.yaml``/``.yml``) and TOML (``.toml``, steps as ``[[steps]]``) are accepted. Steps run
in order; every command resumes, so re-running a config after an interruption is cheap.
A step fails the run (after writing the report so far) unless it has ``allow_failure: true``.
"""

from __future__ import annotations

import json
import logging
import os
import shlex
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ParameterError
from ..io.atomic import atomic_path
from .workflow_config import parse_config

__all__ = ["Step", "StepResult", "Workflow", "load_workflow", "run_workflow"]

log = logging.getLogger(__name__)


@dataclass
class Step:
    name: str
    run: list[str]
    images: list[str] = field(default_factory=list)
    links: list[str] = field(default_factory=list)
    allow_failure: bool = False
    note: str = ""


@dataclass
class Workflow:
    name: str
    steps: list[Step]
    source: str = ""
    intro: str = ""


@dataclass
class StepResult:
    step: Step
    exit_code: int
    stdout: str
    stderr: str
    seconds: float


def load_workflow(
    path: str | os.PathLike, *, out_dir: str | os.PathLike, overrides: dict | None = None
) -> Workflow:
    """Read a YAML/TOML workflow config (checked by :mod:`.workflow_config`), substituting
    ``${vars}`` (``out`` = ``out_dir``)."""
    cfg = parse_config(path, out_dir=out_dir, overrides=overrides)
    return Workflow(
        name=cfg["name"],
        steps=[Step(**s) for s in cfg["steps"]],
        source=str(path),
        intro=cfg["intro"],
    )


#: Runs one command line in-process: ``run(args) -> (exit code, stdout, stderr)``. The command
#: line layer provides it (this layer never imports it).
CommandRunner = Callable[[list[str]], tuple[int, str, str]]


def _run_step(step: Step, run_command: CommandRunner) -> StepResult:
    t0 = time.perf_counter()
    code, stdout, stderr = run_command(step.run)
    return StepResult(step, code, stdout, stderr, time.perf_counter() - t0)


#: Largest ``steps.json`` read (bytes): it holds each step's captured output.
MAX_STEPS_BYTES = 64 << 20
#: Fields of a ``steps.json`` row and their kinds (:func:`sparsetools.io.sidecar.check_fields`).
STEP_FIELDS = {"name": "str", "run": "list", "exit_code": "int", "seconds": "number",
               "stdout": "str", "stderr": "str"}  # fmt: skip


def _previous_results(workflow: Workflow, path: Path) -> dict[str, StepResult]:
    """Results of an earlier run (``steps.json``) by step name, for steps still in the config.

    The file is untrusted input: a regular file (not a link) of at most
    :data:`MAX_STEPS_BYTES`, a list of rows whose every field has its kind; anything else is
    one :class:`FormatError` naming the file (and the row and field)."""
    from ..errors import FormatError
    from ..io.sidecar import check_fields, read_json_document

    hint = "; run without --only to rewrite it"
    try:
        rows = read_json_document(path, what="pipeline steps record", max_bytes=MAX_STEPS_BYTES,
                                  follow_links=False, hint=hint)  # fmt: skip
    except FileNotFoundError:
        return {}
    if not isinstance(rows, list):
        raise FormatError(f"{path}: not a pipeline steps record (a JSON list){hint}")
    steps = {s.name: s for s in workflow.steps}
    out = {}
    for i, r in enumerate(rows):
        where = f"{path}: row {i}"
        if not isinstance(r, dict):
            raise FormatError(f"{where} is not a JSON object{hint}")
        try:
            check_fields(r, STEP_FIELDS, where)
            if not all(isinstance(a, str) for a in r["run"]):
                raise FormatError(f"{where}: 'run' must be a list of strings")
        except FormatError as exc:
            raise FormatError(f"{exc}{hint}") from exc
        step = steps.get(r["name"])
        if step is None:
            continue
        if r["run"] != step.run:
            continue  # the step's command changed since: its old output no longer describes it
        out[step.name] = StepResult(
            step, r["exit_code"], r["stdout"], r["stderr"], float(r["seconds"])
        )
    return out


def run_workflow(
    workflow: Workflow,
    out_dir: str | os.PathLike,
    *,
    run_command: CommandRunner,
    only: list[str] | None = None,
    echo=print,
    overwrite: bool = False,
) -> list[StepResult]:
    """Run the steps in order and write ``OUT/report.md``; raise on the first failing step.

    Every command resumes (outputs that are up to date are kept), so a second run is cheap and
    rewrites the report. With ``only``, just those steps run and the report keeps the other
    steps' sections from the previous run (``OUT/steps.json``).

    ``report.md`` and ``steps.json`` are replaced only when the pipeline wrote them (their
    record says so) or with ``overwrite``: a user's own ``report.md`` in ``-o`` is refused
    before any step runs.
    """
    from ..io.containment import check_contained
    from .core import check_output_dir
    from .output_file import OutputFile

    out = check_output_dir(out_dir, [])
    written = [OutputFile(out / name, "pipeline", {}, [], overwrite=overwrite, noun="a report")
               for name in ("report.md", "steps.json")]  # fmt: skip
    for f in written:
        check_contained(out, f.path)
        f.up_to_date()  # refuses a file the pipeline did not write
    names = [s.name for s in workflow.steps]
    if only:
        unknown = [n for n in only if n not in names]
        if unknown:
            raise ParameterError(
                f"no step named {unknown[0]!r} in {workflow.source} (steps: {', '.join(names)})",
                param="only",
            )
    previous = _previous_results(workflow, out / "steps.json") if only else {}
    results: list[StepResult] = []
    failed: StepResult | None = None
    for i, step in enumerate(workflow.steps):
        if only and step.name not in only:
            continue
        echo(f"[{i + 1}/{len(workflow.steps)}] {step.name}: sparsetools {shlex.join(step.run)}")
        res = _run_step(step, run_command)
        results.append(res)
        echo(f"    -> exit {res.exit_code} in {res.seconds:.1f} s")
        if res.exit_code != 0 and not step.allow_failure:
            failed = res
            break
    ran = {r.step.name: r for r in results}
    shown = [ran.get(s.name) or previous.get(s.name) for s in workflow.steps]
    shown = [r for r in shown if r is not None]
    write_report(workflow, shown, out / "report.md")
    steps = [
        {
            "name": r.step.name,
            "run": r.step.run,
            "exit_code": r.exit_code,
            "seconds": round(r.seconds, 2),
            "stdout": r.stdout,
            "stderr": r.stderr,
        }
        for r in shown
    ]
    with atomic_path(out / "steps.json") as tmp:
        tmp.write_text(json.dumps(steps, indent=1), encoding="utf-8")
    for f in written:
        f.record()
    if failed is not None:
        last = (failed.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise ParameterError(f"step '{failed.step.name}' failed (exit {failed.exit_code}): {last}")
    return results


def _relative(p: Path, report: Path) -> str:
    """``p`` as a link from the report's folder (absolute where no relative path exists)."""
    try:
        return os.path.relpath(p, report.parent)
    except ValueError:
        return str(p)


def write_report(workflow: Workflow, results: list[StepResult], path: Path) -> None:
    """Markdown report: one section per step with its command, output, pictures (shown) and
    links (other files the step wrote: an HTML page, a video), those that exist."""
    lines = [f"# {workflow.name}", ""]
    if workflow.intro:
        lines += [workflow.intro.strip(), ""]
    lines += [
        f"Config: `{workflow.source}`",
        "",
        "| step | exit | seconds |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {r.step.name} | {r.exit_code} | {r.seconds:.1f} |" for r in results]
    lines.append("")
    for r in results:
        lines += [
            f"## {r.step.name}",
            "",
            "```",
            f"sparsetools {shlex.join(r.step.run)}",
            "```",
            "",
        ]
        if r.step.note:
            lines += [r.step.note.strip(), ""]
        if r.stdout.strip():
            lines += ["```", r.stdout.rstrip(), "```", ""]
        if r.exit_code != 0 and r.stderr.strip():
            lines += ["Error output:", "", "```", r.stderr.rstrip(), "```", ""]
        for im in r.step.images:
            p = Path(im)
            if p.exists():
                lines += [f"![{p.stem}]({_relative(p, path)})", ""]
        for link in r.step.links:
            p = Path(link)
            if p.exists():
                lines += [f"[{p.name}]({_relative(p, path)})", ""]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
