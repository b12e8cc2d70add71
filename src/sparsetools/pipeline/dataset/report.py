"""``dataset report``: one static HTML page that shows a whole dataset at once.

The page holds, per split, the counts of ``dataset info``, its sequences and sources and what
the dataset records about how its samples (and their ground truth) were made; histograms of
density and depth (:mod:`.report_plots`, matplotlib); thumbnails of the frames of lowest and
highest density (sparse depth over the image); the checks of ``dataset verify`` and their
outcome; and, from the results of ``sparsetools eval``, the per-image metrics of a trained
model, worst frames first.

The page is one self-contained file: every picture is embedded as a ``data:`` URI, there is no
script, no style sheet or font to fetch and no link to anything but the page's own sections,
so it can be mailed, attached to an issue or opened from an archive as it is. It is written
atomically; an existing file is replaced only when ``dataset report`` wrote it (its record says
so), like every output of sparsetools.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from html import escape
from pathlib import Path

import numpy as np

from ..._version import __version__
from ...errors import FormatError, ParameterError
from ...io.dataset import MANIFEST_NAME, ManifestRow
from ...validate import check_int_range
from .inspect import DatasetInfo, _human, dataset_info
from .report_data import (
    EVAL_METRIC,
    EvalResults,
    colour_scale_max,
    depth_samples,
    find_eval_results,
    generation_summary,
    pick_thumbnails,
    read_eval_results,
    thumbnail,
)
from .verify import VerifyReport, verify_dataset

__all__ = ["ReportSettings", "ReportSummary", "render_dataset_report", "write_dataset_report"]

#: Suffixes of the page.
PAGE_SUFFIXES = (".html", ".htm")
#: Most evaluated images listed (the worst); the results file holds them all.
MAX_EVAL_ROWS = 100
#: Most sequence names listed per split, and problems / warnings of verify listed.
MAX_NAMES = 30
MAX_PROBLEMS = 200
#: Columns of the per-image eval table, where the results file has them.
EVAL_COLUMNS = ("rmse", "mae", "abs_rel", "irmse", "delta1", "n_pixels", "n_holes", "scale")
#: Units of the metrics (those of sparsetools.ops.metrics), shown in the table's head.
EVAL_UNITS = {"rmse": "m", "mae": "m", "irmse": "1/km"}


@dataclass(frozen=True)
class ReportSettings:
    """What the page shows (recorded with it: another setting is refused without --overwrite).

    Attributes
    ----------
    thumbnails : int
        Frames per group of thumbnails (lowest density, highest density, spread); 0: none.
    eval : str, optional
        The ``--eval`` run folder or results file, absolute.
    """

    thumbnails: int = field(default=4, metadata={"option": "--thumbnails"})
    eval: str | None = field(default=None, metadata={"option": "--eval"})


@dataclass(frozen=True)
class ReportSummary:
    """What ``dataset report`` did.

    Attributes
    ----------
    path : str
    status : {"written", "up to date"}
    samples, splits, thumbnails, eval_images : int
        What the page shows (0 when it was up to date and not rewritten).
    problems : int
        Problems ``verify`` found (the page lists them); -1 when not rewritten.
    bytes : int
        Size of the page.
    """

    path: str
    status: str
    samples: int = 0
    splits: int = 0
    thumbnails: int = 0
    eval_images: int = 0
    problems: int = -1
    bytes: int = 0


# -- the checks of verify, and which problems belong to each --------------------------------------
#: (check, message fragments of inspect._verify_* that report a failure of it), in the order the
#: problems are attributed: the first check with a matching fragment takes the problem.
_CHECKS = (
    ("inputs unchanged since the build", ("changed since the build",)),
    ("SHA-256 of every file and of the points match the manifest", ("has changed",)),
    ("n_sparse, n_gt and density match the data", ("points, the manifest says", "density ")),
    (
        "sparse points: right row and size, inside the image, one per pixel, positive finite "
        "depths; PNG and Parquet agree",
        (" row ", "disagree", "no sparse depth", ".parquet"),
    ),
    (
        "every file decodable and of the manifest's image size",
        ("cannot be decoded", "the manifest says", "bad image size"),
    ),
    (
        "every file inside the dataset, present and readable",
        ("is missing", "cannot be read", "outside", "link", "no such"),
    ),
)
#: The order the checks are listed in.
_CHECK_ORDER = (5, 4, 1, 3, 2, 0)


def check_outcomes(report: VerifyReport) -> list[tuple[str, list[str]]]:
    """Each check of ``verify`` with the problems that belong to it (empty: passed); problems
    of no known check last, as ``other problems`` (listed only when there are some)."""
    found: list[list[str]] = [[] for _ in _CHECKS]
    other = []
    for p in report.problems:
        for i, (_, fragments) in enumerate(_CHECKS):
            if any(f in p for f in fragments):
                found[i].append(p)
                break
        else:
            other.append(p)
    out = [(_CHECKS[i][0], found[i]) for i in _CHECK_ORDER]
    return out + ([("other problems", other)] if other else [])


# -- HTML ------------------------------------------------------------------------------------------
_STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; color: #222; margin: 0 auto; max-width: 1240px;
       padding: 16px 24px 48px; }
h1 { font-size: 24px; margin: 8px 0 4px; } h2 { font-size: 19px; margin: 28px 0 8px;
     border-bottom: 1px solid #ccc; padding-bottom: 3px; } h3 { font-size: 16px; margin: 18px 0 6px; }
h4 { font-size: 14px; margin: 10px 0 4px; color: #444; }
table { border-collapse: collapse; margin: 6px 0 10px; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #f2f2f2; } td.n { text-align: right; font-variant-numeric: tabular-nums; }
code { font-size: 13px; } .meta { color: #555; margin: 2px 0; }
.ok { color: #1a7f37; font-weight: 600; } .bad { color: #c62828; font-weight: 600; }
.warn { color: #9a6700; font-weight: 600; }
nav a { margin-right: 14px; }
.grid { display: grid; grid-template-columns: repeat(auto-fill, minmax(270px, 1fr)); gap: 10px; }
figure { margin: 0; } figure img { width: 100%; height: auto; display: block; border: 1px solid #ddd; }
figcaption { font-size: 12px; color: #333; padding-top: 2px; overflow-wrap: anywhere; }
img.plot { max-width: 100%; height: auto; display: block; }
img.bar { width: 320px; height: 14px; display: block; }
.scale { display: flex; justify-content: space-between; width: 320px; font-size: 12px; }
ul.problems { max-height: 320px; overflow: auto; font-size: 12px; }
"""


def _e(value) -> str:
    return escape(str(value), quote=True)


def _num(v) -> str:
    """A number for a table: integers with thousands separators, others with 3 decimals
    (4 significant digits from 1000 on or below 0.01)."""
    if v is None:
        return "–"
    if isinstance(v, int):
        return f"{v:,}"
    if not np.isfinite(v):
        return str(v)
    return f"{v:.3f}" if v == 0 or 0.01 <= abs(v) < 1000 else f"{v:.4g}"


def _table(head: list[str], rows: list[list[str]], *, attrs: list[str] | None = None) -> str:
    """A table from cells that are already HTML (callers escape what they put in)."""
    out = ["<table>"]
    if head:
        out.append("<tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>")
    for i, r in enumerate(rows):
        extra = f" {attrs[i]}" if attrs else ""
        cells = "".join(c if c.startswith(("<td", "<th")) else f"<td>{c}</td>" for c in r)
        out.append(f"<tr{extra}>{cells}</tr>")
    out.append("</table>")
    return "\n".join(out)


def _n(v) -> str:
    return f'<td class="n">{_num(v)}</td>'


def _spread(values: list[float], fmt: str = ".3g") -> str:
    """``median (min – max)`` of values."""
    if not values:
        return "–"
    v = np.asarray(values, dtype=np.float64)
    return f"{np.median(v):{fmt}} ({v.min():{fmt}} – {v.max():{fmt}})"


def _summary_section(info: DatasetInfo) -> str:
    n, dens = info.n_sparse, info.density_percent
    rows = [
        ["samples", f"{info.samples:,} in {info.sequences:,} sequence(s), {len(info.splits)} split(s)"],
        ["image sizes", ", ".join(f"{_e(k)} ({v:,})" for k, v in info.image_sizes.items())],
        ["sources", ", ".join(f"{_e(k)} ({v:,})" for k, v in info.sources.items())],
        ["with gt / confidence / intrinsics",
         f"{info.with_gt:,} / {info.with_confidence:,} / {info.with_intrinsics:,}"],
    ]  # fmt: skip
    if n.mean is not None:
        rows.append(["sparse points", f"mean {n.mean:.1f}, min {n.min:.0f}, max {n.max:.0f}"])
        rows.append(["density %", f"min {dens.min:.4g}, median {dens.median:.4g}, "
                     f"mean {dens.mean:.4g}, max {dens.max:.4g}"])  # fmt: skip
    sizes = ", ".join(f"{_e(k)} {_human(v)}" for k, v in info.bytes.items())
    rows.append(["size", f"{_human(info.total_bytes)} ({sizes})"])
    if info.missing_files:
        rows.append(["missing files", f'<span class="bad">{info.missing_files:,}</span>'])
    rows = [[f"<th>{k}</th>", v] for k, v in rows]
    return '<h2 id="summary">Summary (dataset info)</h2>\n' + _table([], rows)


def _split_method(method) -> str:
    """The manifest's record of the split assignment, in words."""
    if not isinstance(method, dict):
        return "not recorded"
    parts = []
    for k, v in sorted(method.items()):
        if isinstance(v, dict):
            v = ", ".join(f"{_e(a)} {_e(b)}" for a, b in v.items())
        else:
            v = _e(v)
        parts.append(f"{_e(k)} {v}")
    return "; ".join(parts)


def _splits_section(info: DatasetInfo, by_split: dict[str, list[ManifestRow]]) -> str:
    head = ["split", "samples", "sequences", "with gt", "sources", "image sizes",
            "density % median (min – max)", "gt density %", "sequences (frames)"]  # fmt: skip
    rows, attrs = [], []
    for name, counts in info.splits.items():
        sub = by_split.get(name, [])
        seqs: dict[str, int] = {}
        for r in sub:
            seqs[r.sequence] = seqs.get(r.sequence, 0) + 1
        names = ", ".join(f"{_e(s)} ({c:,})" for s, c in sorted(seqs.items())[:MAX_NAMES])
        if len(seqs) > MAX_NAMES:
            names += f", … {len(seqs) - MAX_NAMES:,} more"
        sources: dict[str, int] = {}
        sizes: dict[str, int] = {}
        for r in sub:
            sources[str(r.source)] = sources.get(str(r.source), 0) + 1
            sizes[f"{r.width}x{r.height}"] = sizes.get(f"{r.width}x{r.height}", 0) + 1
        gt_dens = [100.0 * r.n_gt / (r.width * r.height) for r in sub if r.n_gt is not None]
        rows.append([
            f"<b>{_e(name)}</b>", _n(counts.samples), _n(counts.sequences), _n(counts.with_gt),
            ", ".join(f"{_e(k)} ({v:,})" for k, v in sources.items()),
            ", ".join(f"{_e(k)} ({v:,})" for k, v in sizes.items()),
            _spread([100.0 * r.density for r in sub]), _spread(gt_dens), names,
        ])  # fmt: skip
        attrs.append(f'class="split" data-split="{_e(name)}"')
    text = _table(head, rows, attrs=attrs)
    return (
        '<h2 id="splits">Splits</h2>\n'
        f'<p class="meta">How the splits were assigned: {_split_method(info.split_method)}.'
        f"</p>\n{text}"
    )


def _made_section(rows: list[ManifestRow], meta: dict) -> str:
    head = ["recorded", "value(s)", "samples"]
    lines = []
    for k in sorted(meta):
        if k not in ("split", "schema_version"):
            lines.append([f"<code>{_e(k)}</code> (dataset)", f"<code>{_e(meta[k])}</code>", ""])
    with_gt = sum(r.gt_path is not None for r in rows)
    gt_text = f"{with_gt:,} of {len(rows):,} samples have a gt map"
    if with_gt:
        n_gt = [float(r.n_gt) for r in rows if r.n_gt is not None]
        gt_text += f" (valid pixels per map, median (min – max): {_spread(n_gt, ',.0f')})"
    lines.append(["ground truth", gt_text, _n(with_gt)])
    for p in generation_summary(rows):
        vals = ", ".join(f"<code>{_e(v)}</code>" + (f" ({c:,})" if p.distinct > 1 else "")
                         for v, c in p.values)  # fmt: skip
        if p.distinct > len(p.values):
            vals = f"{p.distinct:,} distinct values, e.g. {vals}"
        lines.append([f"<code>{_e(p.name)}</code>", vals, _n(p.samples)])
    return (
        '<h2 id="made">How the samples were made</h2>\n<p class="meta">What the dataset records: '
        "the build's metadata and each sample's <code>generation_params</code> (nested keys "
        "dotted; <code>inputs.*</code> are the input files of each sample).</p>\n"
        + _table(head, lines)
    )


def _img(uri: str, *, alt: str, cls: str = "", width: int | None = None,
         height: int | None = None) -> str:  # fmt: skip
    size = f' width="{width}" height="{height}"' if width and height else ""
    klass = f' class="{cls}"' if cls else ""
    return f'<img src="{uri}" alt="{_e(alt)}"{klass}{size} />'


def _png_uri(data: bytes) -> str:
    import base64

    return "data:image/png;base64," + base64.b64encode(data).decode("ascii")


def _colour_bar(max_depth: float) -> str:
    import cv2

    from ...ops.colormap import colorize_depth

    ramp = np.linspace(max_depth / 320, max_depth, 320, dtype=np.float32)[None, :].repeat(14, 0)
    _, buf = cv2.imencode(".png", colorize_depth(ramp, max_depth=max_depth)[:, :, ::-1])
    return (
        '<p class="meta">Sparse depth over the image (each point a 3x3 square at thumbnail '
        "size, the nearest on top), coloured from 0 m (blue) to "
        f"{max_depth:g} m (red):</p>\n"
        + _img(_png_uri(buf.tobytes()), alt="colour scale", cls="bar", width=320, height=14)
        + f'\n<div class="scale"><span>0 m</span><span>{max_depth / 2:g} m</span>'
        f"<span>{max_depth:g} m</span></div>"
    )


def _figure(reader, row: ManifestRow, max_depth: float, extra: str = "") -> str:
    """One thumbnail with its caption; a frame whose files cannot be read says so instead
    (``verify`` lists why), so that a damaged dataset still gets its page."""
    caption = (f"<code>{_e(row.id)}</code><br />density {100 * row.density:.3g} %, "
               f"{row.n_sparse:,} points{extra}")  # fmt: skip
    try:
        t = thumbnail(reader, row, max_depth=max_depth)
    except (FormatError, OSError) as exc:
        img = f'<p class="bad unreadable">cannot be drawn: {_e(exc)}</p>'
    else:
        img = _img(t.data_uri(), alt=f"sparse depth over {row.id}", width=t.width,
                   height=t.height)  # fmt: skip
    return f'<figure data-id="{_e(row.id)}">{img}<figcaption>{caption}</figcaption></figure>'


def _thumbnails_section(reader, by_split, n: int, max_depth: float) -> tuple[str, int]:
    if n <= 0:
        return "", 0
    parts, count = ['<h2 id="frames">Frames</h2>', _colour_bar(max_depth)], 0
    for i, (name, rows) in enumerate(by_split.items()):
        parts.append(f'<h3 id="frames-{i}" data-split="{_e(name)}">{_e(name)}</h3>')
        for title, group in pick_thumbnails(rows, n):
            figs = [_figure(reader, r, max_depth) for r in group]
            count += len(figs)
            parts.append(f"<h4>{_e(title)}</h4>\n<div class=\"grid\">\n" + "\n".join(figs)
                         + "\n</div>")  # fmt: skip
    return "\n".join(parts), count


def _plots_section(reader, by_split) -> tuple[str, float]:
    from .report_plots import HistogramPanel, histogram_png

    splits = list(by_split)
    sparse, gt, frames = {}, {}, {}
    for name, rows in by_split.items():
        sparse[name], gt[name], frames[name] = depth_samples(reader, rows)
    density = HistogramPanel("sparse density per frame", "% of pixels with a point",
                             {k: np.array([100 * r.density for r in v]) for k, v in by_split.items()})  # fmt: skip
    gt_density = HistogramPanel(
        "ground-truth density per frame", "% of pixels with a gt value",
        {k: np.array([100 * r.n_gt / (r.width * r.height) for r in v if r.n_gt is not None])
         for k, v in by_split.items()},
    )  # fmt: skip
    depth = HistogramPanel("sparse depth", "depth (m)", sparse)
    gt_depth = HistogramPanel("ground-truth depth", "depth (m)", gt)
    read = ", ".join(f"{_e(k)} {v:,} of {len(by_split[k]):,}" for k, v in frames.items())
    html = "\n".join([
        '<h2 id="plots">Distributions</h2>',
        '<p class="meta">Per split, the share of its frames (density) or of its depth values '
        "(depth) in each bin; the legend gives how many values each curve holds.</p>",
        _img(_png_uri(histogram_png([density, gt_density], splits=splits)),
             alt="density histograms per split", cls="plot", width=1100, height=330),
        _img(_png_uri(histogram_png([depth, gt_depth], splits=splits)),
             alt="depth histograms per split", cls="plot", width=1100, height=330),
        f'<p class="meta">Depths from the frames read (evenly spaced, in id order): {read}; '
        "at most 5,000 values of each kind per frame.</p>",
    ])  # fmt: skip
    all_sparse = np.concatenate([*sparse.values(), np.zeros(0, np.float32)])
    return html, colour_scale_max(all_sparse)


def _verify_section(report: VerifyReport) -> str:
    rows = []
    for check, problems in check_outcomes(report):
        outcome = ('<span class="ok">passed</span>' if not problems
                   else f'<span class="bad">{len(problems):,} problem(s)</span>')  # fmt: skip
        rows.append([_e(check), outcome])
    verdict = (f'<span class="ok">{report.samples:,} sample(s) verified, no problem</span>'
               if report.ok else
               f'<span class="bad">{len(report.problems):,} problem(s)</span>')  # fmt: skip
    parts = ['<h2 id="verify">Checks (dataset verify)</h2>', f"<p>{verdict}</p>",
             _table(["check", "outcome"], rows, attrs=['class="check"'] * len(rows))]  # fmt: skip
    for kind, items, cls in (("problem", report.problems, "bad"),
                             ("warning", report.warnings, "warn")):  # fmt: skip
        if items:
            shown = "".join(f"<li>{_e(p)}</li>" for p in items[:MAX_PROBLEMS])
            more = (f"<li>… {len(items) - MAX_PROBLEMS:,} more (run dataset verify)</li>"
                    if len(items) > MAX_PROBLEMS else "")  # fmt: skip
            parts.append(f'<p class="{cls}">{len(items):,} {kind}(s):</p>'
                         f'<ul class="problems">{shown}{more}</ul>')  # fmt: skip
    return "\n".join(parts)


def _eval_section(results: list[EvalResults], reader, rows_by_id, n: int, max_depth) -> str:
    parts = ['<h2 id="eval">Model evaluation (per image, worst first)</h2>']
    for k, res in enumerate(results):
        what = f"<code>{_e(res.checkpoint)}</code>" if res.checkpoint else "predictions"
        split = f", split <b>{_e(res.split)}</b>" if res.split else ""
        parts.append(f'<h3 id="eval-{k}">{what}{split}</h3>')
        parts.append(f'<p class="meta">From <code>{_e(res.path)}</code>: {len(res.rows):,} '
                     f"image(s), ordered by {EVAL_METRIC} (largest first).</p>")  # fmt: skip
        cols = [c for c in EVAL_COLUMNS if any(c in r for r in res.rows)]
        if res.metrics:
            avg = ", ".join(f"{_e(c)} {_num(res.metrics[c])}" for c in cols if c in res.metrics)
            parts.append(f"<p>Mean over the images: {avg}</p>")
        worst = [rows_by_id[r["id"]] for r in res.rows if r["id"] in rows_by_id][:n]
        if worst:
            metric = {r["id"]: r.get(EVAL_METRIC) for r in res.rows}
            figs = [_figure(reader, row, max_depth, f", {EVAL_METRIC} {_num(metric[row.id])}")
                    for row in worst]  # fmt: skip
            parts.append('<h4>worst frames</h4>\n<div class="grid">\n' + "\n".join(figs)
                         + "\n</div>")  # fmt: skip
        table_rows = []
        for rank, r in enumerate(res.rows[:MAX_EVAL_ROWS], start=1):
            row = rows_by_id.get(r["id"])
            split_name = _e(row.split) if row is not None else "(not in the dataset)"
            table_rows.append([_n(rank), f"<code>{_e(r['id'])}</code>", split_name,
                               *(_n(r.get(c)) for c in cols)])  # fmt: skip
        head = [f"{c} ({EVAL_UNITS[c]})" if c in EVAL_UNITS else c for c in cols]
        parts.append(_table(["#", "id", "split", *head], table_rows,
                            attrs=['class="eval-row"'] * len(table_rows)))  # fmt: skip
        if len(res.rows) > MAX_EVAL_ROWS:
            parts.append(f'<p class="meta">… {len(res.rows) - MAX_EVAL_ROWS:,} more in '
                         f"<code>{_e(res.path)}</code>.</p>")  # fmt: skip
        if res.not_in_dataset:
            parts.append(f'<p class="warn">{res.not_in_dataset:,} evaluated image(s) are not '
                         "samples of this dataset.</p>")  # fmt: skip
    return "\n".join(parts)


def render_dataset_report(
    dataset: str | os.PathLike,
    *,
    thumbnails: int = 4,
    eval_results: Sequence[EvalResults] = (),
    threads: int = 1,
) -> tuple[str, ReportSummary]:
    """The page of a dataset, as HTML text (what :func:`write_dataset_report` writes).

    Parameters
    ----------
    dataset : path-like
    thumbnails : int
        Frames per thumbnail group (:func:`.report_data.pick_thumbnails`); 0: no thumbnails.
    eval_results : list of EvalResults
        Per-image metrics to list (:func:`.report_data.read_eval_results`).
    threads : int
        Threads of the ``verify`` run.
    """
    from ...io.dataset_reader import DatasetReader

    thumbnails = check_int_range(thumbnails, "thumbnails", low=0)
    root = Path(dataset)
    info = dataset_info(root)
    report = verify_dataset(root, threads=threads)
    reader = DatasetReader(root)
    rows = ManifestRow.from_table(reader.manifest)
    by_split: dict[str, list[ManifestRow]] = {name: [] for name in info.splits}
    for r in rows:
        by_split.setdefault(str(r.split), []).append(r)
    plots, max_depth = _plots_section(reader, by_split)
    frames, n_thumbs = _thumbnails_section(reader, by_split, thumbnails, max_depth)
    nav = [("summary", "summary"), ("splits", "splits"), ("made", "how made"),
           ("plots", "distributions"), ("frames", "frames"), ("verify", "checks")]  # fmt: skip
    if not frames:
        nav.remove(("frames", "frames"))
    body = [
        f"<h1>Dataset <code>{_e(root.resolve().name)}</code></h1>",
        f'<p class="meta"><code>{_e(root)}</code> · schema version '
        f"{_e(info.schema_version)} · built by {_e(info.created_by or 'unknown')} · this page "
        f"by sparsetools {__version__} (<code>sparsetools dataset report</code>)</p>",
        "<nav>" + "".join(f'<a href="#{a}">{t}</a>' for a, t in nav)
        + ('<a href="#eval">evaluation</a>' if eval_results else "") + "</nav>",
        _summary_section(info), _splits_section(info, by_split),
        _made_section(rows, dict(reader.info)), plots, frames,
        _verify_section(report),
    ]  # fmt: skip
    if eval_results:
        ids = {r.id: r for r in rows}
        body.append(_eval_section(list(eval_results), reader, ids, thumbnails, max_depth))
    page = (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8" />\n'
        f"<title>Dataset report: {_e(root.resolve().name)}</title>\n"
        f"<style>{_STYLE}</style>\n</head>\n<body>\n"
        + "\n".join(b for b in body if b)
        + "\n</body>\n</html>\n"
    )
    summary = ReportSummary(
        path="", status="written", samples=len(rows), splits=len(by_split), thumbnails=n_thumbs,
        eval_images=sum(len(r.rows) for r in eval_results), problems=len(report.problems),
        bytes=len(page.encode("utf-8")),
    )  # fmt: skip
    return page, summary


def write_dataset_report(
    dataset: str | os.PathLike,
    out: str | os.PathLike,
    *,
    thumbnails: int = 4,
    eval_path: str | os.PathLike | None = None,
    threads: int = 1,
    overwrite: bool = False,
) -> ReportSummary:
    """Write the page of ``dataset`` to ``out`` (atomically), unless it is up to date.

    The page is up to date when ``dataset report`` wrote it with the same settings from the
    same manifest (and eval results); any other existing file is refused unless
    ``overwrite``. Nothing but ``out`` and its record (``.sparsetools/`` beside it) is written.

    Parameters
    ----------
    dataset : path-like
    out : path-like
        The page, ``.html`` or ``.htm``.
    thumbnails : int
    eval_path : path-like, optional
        A train run folder (its ``eval_*.json`` of this dataset) or an eval results file.
    threads : int
    overwrite : bool

    Raises
    ------
    ParameterError, FormatError, OutputError, DependencyError
        A bad ``-o``, an unreadable dataset or eval results, a file that may not be
        replaced, matplotlib missing: before anything is written.
    """
    from ...io.atomic import atomic_write_bytes
    from ...io.containment import check_contained
    from ...io.dataset import read_manifest
    from ..output_file import OutputFile
    from .report_plots import require_matplotlib

    out = Path(out)
    thumbnails = check_int_range(thumbnails, "thumbnails", low=0)
    if out.suffix.lower() not in PAGE_SUFFIXES:
        raise ParameterError("the report is written as .html", param="--out")
    root = Path(dataset)
    manifest = root / MANIFEST_NAME
    table, _ = read_manifest(manifest)
    ids = set(table.column("id").to_pylist())
    eval_files = find_eval_results(eval_path, ids) if eval_path is not None else []
    settings = ReportSettings(
        thumbnails=thumbnails,
        eval=str(Path(eval_path).resolve()) if eval_path is not None else None,
    )
    check_contained(out.parent, out)
    target = OutputFile(out, "dataset report", settings, [manifest, *eval_files],
                        overwrite=overwrite, noun="a dataset report")  # fmt: skip
    if target.up_to_date():
        return ReportSummary(path=str(out), status="up to date", bytes=out.stat().st_size)
    require_matplotlib("dataset report")
    results = [read_eval_results(p, ids) for p in eval_files]
    page, summary = render_dataset_report(root, thumbnails=thumbnails, eval_results=results,
                                          threads=threads)  # fmt: skip
    atomic_write_bytes(out, page.encode("utf-8"))
    target.record()
    return dataclasses.replace(summary, path=str(out))
