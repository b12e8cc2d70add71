"""Plots instead of walls of text (issue 27): ``beams --report --plot``, ``accumulate --plot``
and its one-line summary, ``eval --plot``, the training curves; the panels hold the numbers
the command reports, the PNGs have the size of their grid, and without matplotlib the options
that plot fail with one line naming the ``viz`` extra. Also: labels are drawn once.
"""

from __future__ import annotations

import json
import math
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import DependencyError, ParameterError
from sparsetools.io.image import read_image, write_depth_png
from sparsetools.io.plots import Panel, Series, render_panels, require_matplotlib
from sparsetools.pipeline.plots import (
    REMOVAL_REASONS,
    REMOVALS_PLOT,
    RING_REPORT_PLOT,
    removal_panels,
    ring_report_panels,
)
from sparsetools.train.plots import curve_panels, draw_curves, eval_panels, eval_plot_path

ROOT = Path(__file__).resolve().parent.parent
KITTI_CLOUD = ROOT / "sample_data" / "kitti" / "velodyne" / "000001.bin"
SYNTH = ROOT / "sample_data" / "synthetic"
N_FRAMES = 4


def invoke(*args, quiet=True):
    return CliRunner().invoke(cli, [*(["-q"] if quiet else []), *map(str, args)])


def ok(result):
    assert result.exit_code == 0, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    return result


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from the PNG header, read independently of any image library."""
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", path
    return struct.unpack(">II", head[16:24])


def same(a, b) -> bool:
    """Equal sequences of numbers, NaN equal to NaN (and to None: a missing value)."""
    a = [math.nan if v is None else float(v) for v in a]
    b = [math.nan if v is None else float(v) for v in b]
    return len(a) == len(b) and all(
        (math.isnan(x) and math.isnan(y)) or x == y for x, y in zip(a, b, strict=True)
    )


@pytest.fixture
def no_matplotlib(monkeypatch):
    """matplotlib cannot be imported (None in sys.modules halts an import)."""
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)


def one_error_line(result, *, code=1) -> str:
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, result.stderr
    return lines[0]


# -- the helper ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("n", "columns", "grid"), [(1, 2, (1, 1)), (3, 2, (2, 2)), (4, 3, (2, 3))])
def test_a_picture_has_the_size_of_its_grid(n, columns, grid):
    panels = [
        Panel(f"p{k}", "x", "y", (Series("a", [1, 2, 3], [1.0, math.nan, 3.0 + k]),))
        for k in range(n)
    ]
    img = render_panels(panels, columns=columns, panel_size=(200, 150))
    rows, cols = grid
    assert img.shape == (rows * 150, cols * 200, 3) and img.dtype == np.uint8
    # something drawn (lines, text), not a blank canvas
    assert len(np.unique(img.reshape(-1, 3), axis=0)) > 10


def test_every_kind_draws_and_bad_input_is_refused():
    for kind in ("line", "bar", "stacked-bar", "hist"):
        panel = Panel("t", "x", "y", (Series("a", [0, 1], [2, 3]), Series("b", [0, 1], [1, 0])),
                      kind=kind, xticklabels=("u", "v") if "bar" in kind else ())  # fmt: skip
        assert render_panels([panel], panel_size=(160, 120)).shape == (120, 160, 3)
    # an empty histogram and a line without any finite value still draw
    empty = Panel("t", "x", "y", (Series("", [], []),), kind="hist")
    nans = Panel("t", "x", "y", (Series("", [1, 2], [math.nan, math.nan]),))
    assert render_panels([empty, nans], panel_size=(160, 120)).shape == (120, 320, 3)
    with pytest.raises(ParameterError, match="unknown panel kind"):
        Panel("t", "x", "y", (), kind="pie")
    with pytest.raises(ParameterError, match="nothing to plot"):
        render_panels([])


def test_missing_matplotlib_is_one_line(no_matplotlib):
    with pytest.raises(DependencyError) as info:
        require_matplotlib("beams --report --plot")
    msg = str(info.value)
    assert msg == "beams --report --plot needs matplotlib: pip install 'sparsetools[viz]'"
    assert "\n" not in msg


# -- training curves -------------------------------------------------------------------------------


def test_curve_panels_hold_the_metrics_rows():
    history = [
        {"epoch": 1, "train_loss": 2.0, "val_loss": 2.5, "rmse": 9.0},
        {"epoch": 2, "train_loss": 1.0, "val_loss": "", "rmse": 7.5},
        {"epoch": 3, "train_loss": 0.5, "val_loss": 1.5, "rmse": 6.0},
    ]
    loss, metric = curve_panels(history, loss_name="berhu", metric="rmse")
    assert loss.title == "berhu loss" and [s.name for s in loss.series] == ["train", "validation"]
    assert loss.series[0].x == (1.0, 2.0, 3.0)
    assert same(loss.series[0].y, [2.0, 1.0, 0.5])
    assert same(loss.series[1].y, [2.5, None, 1.5])  # the missing value is left out
    assert same(metric.series[0].y, [9.0, 7.5, 6.0]) and metric.ylabel == "RMSE (m)"
    other = curve_panels([dict(history[0], delta1=0.9)], metric="delta1")[1]
    assert other.title == "validation delta1" and same(other.series[0].y, [0.9])
    img = draw_curves(history)
    assert img.shape == (300, 880, 3)
    assert draw_curves(history[:1]).shape == img.shape  # one epoch (a flat range) draws too


# -- beams --report --plot -------------------------------------------------------------------------


def test_beams_report_plot(tmp_path):
    out = tmp_path / "rings"
    text = ok(invoke("beams", "--report", "--plot", KITTI_CLOUD, "-o", out))
    plot = out / RING_REPORT_PLOT
    assert png_size(plot) == (880, 640)  # 2 x 2 panels of 440 x 320
    assert read_image(plot).shape == (640, 880, 3)
    # with the plot, one line per cloud instead of the table (and where the plot is)
    lines = text.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith(str(KITTI_CLOUD)) and "64 rings" in lines[0]
    assert lines[1] == f"plot: {plot}"
    assert sorted(p.name for p in out.iterdir()) == [".sparsetools", RING_REPORT_PLOT]
    # the panels hold what --json reports
    reported = json.loads(ok(invoke("beams", "--report", "--json", KITTI_CLOUD)).stdout)
    table = reported[0]["table"]
    pts, far_pts, el, far_el = ring_report_panels(reported)
    ring = [r["ring"] for r in table]
    assert pts.series[0].x == tuple(float(k) for k in ring) and len(ring) == 64
    assert same(pts.series[0].y, [r["points"] for r in table])
    assert same(far_pts.series[0].y, [r["far_points"] for r in table])
    assert same(el.series[0].y, [r["elevation_deg"] for r in table])
    assert same(far_el.series[0].y, [r["far_elevation_deg"] for r in table])
    assert sum(pts.series[0].y) == reported[0]["points"]
    # rerun: its own plot is replaced; a file it did not write is refused
    ok(invoke("beams", "--report", "--plot", KITTI_CLOUD, "-o", out))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / RING_REPORT_PLOT).write_bytes(b"mine")
    r = invoke("beams", "--report", "--plot", KITTI_CLOUD, "-o", foreign)
    assert "--overwrite" in one_error_line(r)
    assert (foreign / RING_REPORT_PLOT).read_bytes() == b"mine"


def test_beams_plot_needs_report_and_out(tmp_path):
    r = invoke("beams", "--plot", KITTI_CLOUD, "-o", tmp_path / "x")
    assert r.exit_code == 2 and "--plot goes with --report" in r.stderr
    r = invoke("beams", "--report", "--plot", KITTI_CLOUD)
    assert r.exit_code == 2 and "give -o OUT" in r.stderr


def test_beams_plot_without_matplotlib(tmp_path, no_matplotlib):
    out = tmp_path / "rings"
    line = one_error_line(invoke("beams", "--report", "--plot", KITTI_CLOUD, "-o", out))
    assert line == "Error: beams --report --plot needs matplotlib: pip install 'sparsetools[viz]'"
    assert not out.exists()
    # the text report does not need it
    ok(invoke("beams", "--report", KITTI_CLOUD))


# -- accumulate ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def video(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("video") / "video"
    r = invoke("synth-scene", "-o", out, "--video", "--static", "--sequences", 2, "--frames",
               N_FRAMES, "--image-size", "208x64", "--seed", 3)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    return out


def test_accumulate_prints_one_line_and_per_frame_lines_with_verbose(video, tmp_path):
    reported = json.loads(
        ok(invoke("accumulate", video, "-o", tmp_path / "j", "--neighbours", 1, "--json")).stdout
    )
    per_frame = reported["removed_per_frame"]
    assert len(per_frame) == 2 * N_FRAMES
    for quiet in (True, False):
        r = ok(invoke("accumulate", video, "-o", tmp_path / f"a{quiet}", "--neighbours", 1,
                      quiet=quiet))  # fmt: skip
        lines = r.stdout.splitlines()
        assert len(lines) == 1, lines
        line = lines[0]
        assert line.startswith(f"accumulated {2 * N_FRAMES} of {2 * N_FRAMES} frames in ")
        for reason in REMOVAL_REASONS:
            assert f"{reason} {reported['removed'][reason]}" in line
        assert f"kept {reported['kept']} of {reported['points']} points" in line
    # -v after the command, or before it: one line per frame, then the totals
    for args in (["accumulate", "-v"], ["-v", "accumulate"]):
        out = tmp_path / f"v{len(args[0])}"
        r = ok(CliRunner().invoke(cli, [*args, str(video), "-o", str(out), "--neighbours", "1"]))
        lines = r.stdout.splitlines()
        for fid, counts in per_frame.items():
            mine = [ln for ln in lines if ln.startswith(f"{fid}: ")]
            assert len(mine) == 1, (fid, lines)
            for reason, n in counts.items():
                assert f"{reason} {n}" in mine[0]
        assert any(ln.startswith("removed ") and "behind_camera" in ln for ln in lines)
        assert len(lines) > 2 * N_FRAMES + 5


def test_accumulate_plot(video, tmp_path):
    out = tmp_path / "acc"
    r = ok(invoke("accumulate", video, "-o", out, "--neighbours", 1, "--plot", "--json"))
    reported = json.loads(r.stdout)
    plot = out / REMOVALS_PLOT
    assert reported["plot"] == str(plot)
    assert png_size(plot) == (900, 360)
    (panel,) = removal_panels(reported)
    ids = list(reported["removed_per_frame"])
    assert panel.kind == "stacked-bar" and len(panel.xticklabels) == len(ids) == 2 * N_FRAMES
    assert [s.name for s in panel.series] == list(REMOVAL_REASONS)
    for s in panel.series:
        assert same(s.y, [reported["removed_per_frame"][f][s.name] for f in ids])
        assert sum(s.y) == reported["removed"][s.name]
    # one sequence: its name in the axis label, the frame names on the ticks
    one = {
        "removed_per_frame": {f"seq/{k:03d}": dict.fromkeys(REMOVAL_REASONS, k) for k in range(3)}
    }
    (p1,) = removal_panels(one)
    assert p1.xlabel == "frame of seq" and p1.xticklabels == ("000", "001", "002")
    # thousands of frames: lines, no tick labels
    many = {"removed_per_frame": {f"s/{k}": dict.fromkeys(REMOVAL_REASONS, 1) for k in range(500)}}
    (pm,) = removal_panels(many)
    assert pm.kind == "line" and not pm.xticklabels and len(pm.series[0].y) == 500
    # the text line names the plot
    r = ok(invoke("accumulate", video, "-o", out, "--neighbours", 1, "--plot"))
    assert r.stdout.splitlines()[0].endswith(f"plot {plot} (-v: totals and per frame)")


def test_accumulate_plot_without_matplotlib(video, tmp_path, no_matplotlib):
    out = tmp_path / "acc"
    line = one_error_line(invoke("accumulate", video, "-o", out, "--neighbours", 1, "--plot"))
    assert line == "Error: accumulate --plot needs matplotlib: pip install 'sparsetools[viz]'"
    assert not out.exists()  # refused before any frame was computed


# -- eval --plot -----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def depth_pair(tmp_path_factory) -> tuple[Path, Path]:
    """Ground truth 2-70 m and a prediction off by +10 % (and a hole), three frames."""
    root = tmp_path_factory.mktemp("evalpair")
    rng = np.random.default_rng(0)
    for k in range(3):
        gt = rng.uniform(2.0, 70.0, (24, 40)).astype(np.float32)
        gt[rng.random(gt.shape) < 0.3] = 0
        pred = gt * (1.1 + 0.05 * k)
        pred[0, 0] = 0
        write_depth_png(root / "gt" / f"{k:06d}.png", gt)
        write_depth_png(root / "pred" / f"{k:06d}.png", np.where(gt > 0, pred, 20.0))
    return root / "pred", root / "gt"


def test_eval_plot(depth_pair, tmp_path):
    pred, gt = depth_pair
    res = tmp_path / "m.json"
    r = ok(invoke("eval", "--pred", pred, "--gt", gt, "-o", res, "--plot", "--json"))
    brief = json.loads(r.stdout)
    plot = eval_plot_path(res)
    assert plot == tmp_path / "m.png" and str(plot) in brief["written"]
    assert png_size(plot) == (1320, 320)
    full = json.loads(res.read_text())
    bins = full["depth_bins"]
    assert bins == brief["depth_bins"]
    assert bins["edges_m"] == [0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0]
    # pooled errors by bin, against a reference computed here from the files
    from sparsetools.io.depth_files import read_depth_file

    g = np.concatenate([read_depth_file(f).ravel() for f in sorted(gt.glob("*.png"))])
    p = np.concatenate([read_depth_file(f).ravel() for f in sorted(pred.glob("*.png"))])
    g, p = g.astype(np.float64), p.astype(np.float64)
    valid = (g > 1e-3) & (g < 80.0) & (p > 0)  # --fill none: the hole is left out
    err = np.clip(p[valid], 1e-3, 80.0) - g[valid]
    which = np.digitize(g[valid], bins["edges_m"]) - 1
    assert sum(bins["pixels"]) == full["metrics"]["n_pixels"] == int(valid.sum())
    for k in range(len(bins["pixels"])):
        sel = which == k
        assert bins["pixels"][k] == int(sel.sum())
        if sel.any():
            assert bins["mae"][k] == pytest.approx(np.abs(err[sel]).mean(), rel=1e-9)
            assert bins["rmse"][k] == pytest.approx(np.sqrt((err[sel] ** 2).mean()), rel=1e-9)
        else:
            assert bins["mae"][k] is None and bins["rmse"][k] is None
    # the panels hold the reported numbers
    depth, rmse, absrel = eval_panels(full)
    assert same(depth.series[0].y, bins["mae"]) and same(depth.series[1].y, bins["rmse"])
    assert depth.xticklabels[0] == "0-5" and depth.xticklabels[-1] == "70-80"
    assert same(rmse.series[0].y, [row["rmse"] for row in full["per_image"]])
    assert same(absrel.series[0].y, [row["abs_rel"] for row in full["per_image"]])
    # per-image rows and the CSV are as without --plot
    assert "depth_bins" not in full["per_image"][0]
    plain = tmp_path / "plain.json"
    ok(invoke("eval", "--pred", pred, "--gt", gt, "-o", plain))
    assert "depth_bins" not in json.loads(plain.read_text())
    assert plain.with_suffix(".csv").read_text() == res.with_suffix(".csv").read_text()
    assert not plain.with_suffix(".png").exists()


def test_eval_plot_needs_out_and_matplotlib(depth_pair, tmp_path, monkeypatch):
    pred, gt = depth_pair
    r = invoke("eval", "--pred", pred, "--gt", gt, "--plot")
    assert r.exit_code == 2 and "give -o with --pred" in r.stderr
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    res = tmp_path / "m.json"
    line = one_error_line(invoke("eval", "--pred", pred, "--gt", gt, "-o", res, "--plot"))
    assert line == "Error: eval --plot needs matplotlib: pip install 'sparsetools[viz]'"
    assert not res.exists()


# -- labels drawn once -----------------------------------------------------------------------------


def test_label_is_drawn_once_with_its_outline_around_the_same_letters():
    """The white letters lie inside their black outline; no black-only copy of the text sticks
    out beyond the outline (what two putText calls of different thickness gave)."""
    import cv2

    from sparsetools.ops.text import put_outlined_text
    from sparsetools.ops.viz import label_panel

    grey = np.full((40, 400, 3), 128, np.uint8)
    text = "frame 5: one scan, 3.3% of pixels"

    def strays(img):
        """Changed pixels farther than the outline (+ anti-aliasing) from any letter pixel."""
        letters = (img > 160).all(axis=2)
        near = cv2.dilate(letters.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        return int(((img != 128).any(axis=2) & ~near).sum())

    out = label_panel(grey, text, scale=0.6)
    assert (out > 160).all(axis=2).sum() > 100 and (out < 60).all(axis=2).sum() > 50
    assert strays(out) == 0
    # the check catches the old drawing: black with a thick stroke, then white with a thin one
    old = grey.copy()
    cv2.putText(old, text, (5, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(old, text, (5, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255,) * 3, 1, cv2.LINE_AA)
    assert strays(old) > 20
    # the letters span the width OpenCV gives for their own stroke
    (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 1)
    cols = np.flatnonzero((out > 160).all(axis=2).any(axis=0))
    assert w - 6 <= cols[-1] - cols[0] <= w + 2
    # clipped at the border without error; empty text changes nothing
    edge = put_outlined_text(grey.copy(), "edge", (390, 5), scale=0.6)
    assert edge.shape == grey.shape
    assert np.array_equal(put_outlined_text(grey.copy(), "", (5, 20), scale=0.6), grey)


def test_depth_bins_of_one_image_edges_and_empty():
    from sparsetools.ops.metrics import aggregate_depth_bins, depth_bin_edges, depth_metrics

    assert depth_bin_edges(80.0) == (0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0)
    assert depth_bin_edges(7.5) == (0.0, 5.0, 7.5) and depth_bin_edges(3.0) == (0.0, 3.0)
    gt = np.array([[4.0, 5.0, 9.0, 0.0]])  # 5.0 lies on an edge: the upper bin [5, 10)
    pred = np.array([[5.0, 7.0, 9.0, 3.0]])
    m = depth_metrics(pred, gt, bin_edges=(0.0, 5.0, 10.0))
    assert m["depth_bins"] == {
        "pixels": [1, 2],
        "abs_err_sum": [1.0, 2.0],
        "sq_err_sum": [1.0, 4.0],
    }
    assert m["mae"] == pytest.approx(1.0)  # the same pixels as the metrics
    empty = depth_metrics(pred, np.zeros_like(gt), bin_edges=(0.0, 5.0, 10.0))
    assert empty["n_pixels"] == 0 and empty["depth_bins"]["pixels"] == [0, 0]
    pooled = aggregate_depth_bins([m, empty, m], (0.0, 5.0, 10.0))
    assert pooled["pixels"] == [2, 4] and pooled["mae"] == [1.0, 1.0]
    assert pooled["rmse"] == [1.0, pytest.approx(math.sqrt(2.0))]
    assert aggregate_depth_bins([empty], (0.0, 5.0, 10.0))["mae"] == [None, None]
    for bad in ((5.0,), (0.0, 5.0, 5.0), (10.0, 0.0)):
        with pytest.raises(ParameterError, match="bin-edges"):
            depth_metrics(pred, gt, bin_edges=bad)


def test_nothing_imports_matplotlib_until_a_plot_is_drawn():
    code = (
        "import sys, sparsetools.cli.main, sparsetools.cli.beams, sparsetools.cli.accumulate, "
        "sparsetools.cli.eval, sparsetools.io.plots, sparsetools.pipeline.plots, "
        "sparsetools.train.plots, sparsetools.train.results; "
        "print('matplotlib' in sys.modules)"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_train_without_matplotlib_is_one_line(tmp_path, no_matplotlib):
    pytest.importorskip("torch")
    (tmp_path / "ds").mkdir()
    line = one_error_line(invoke("train", tmp_path / "ds", "-o", tmp_path / "run"))
    assert line == "Error: train (its curves.png) needs matplotlib: pip install 'sparsetools[viz]'"
    assert not (tmp_path / "run").exists()
