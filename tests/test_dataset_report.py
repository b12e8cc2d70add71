"""``sparsetools dataset report``: the HTML page of a dataset, checked as a document and in a
real browser (headless Chromium, when installed)."""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.dataset import ManifestRow, read_manifest
from sparsetools.io.depth_files import read_depth_file
from sparsetools.io.image import write_depth_png, write_image
from sparsetools.pipeline.dataset import dataset_info

SAMPLE = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"
#: Elements without an end tag in HTML.
VOID = {"meta", "img", "br", "hr", "link", "input", "source", "wbr"}


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


@pytest.fixture(scope="module")
def sample_ds(tmp_path_factory) -> Path:
    """The three synthetic sample frames, one sequence each, so one frame per split."""
    tmp = tmp_path_factory.mktemp("report")
    res = run("project", SAMPLE / "velodyne", "--calib", SAMPLE / "calib", "--image",
              SAMPLE / "image_2", "-o", tmp / "lidar", "--format", "parquet", "-q")  # fmt: skip
    assert res.exit_code == 0, res.output
    res = run("dataset", "build", "-o", tmp / "ds", "--rgb", SAMPLE / "image_2", "--sparse",
              tmp / "lidar", "--gt", SAMPLE / "depth_gt", "--calib", tmp / "lidar" / "calib",
              "--sequence-from", r"regex:^(\d{6})", "--splits", "train=0.4,val=0.3,test=0.3",
              "--source", "lidar-64", "-q")  # fmt: skip
    assert res.exit_code == 0, res.output
    return tmp / "ds"


@pytest.fixture(scope="module")
def eval_file(sample_ds, tmp_path_factory) -> Path:
    """Real results of ``eval --pred --gt``: frame k predicted as gt * (1 + 0.1 (k + 1)), so the
    error grows with k and 000002 is the worst frame."""
    tmp = tmp_path_factory.mktemp("eval")
    for k, gt_path in enumerate(sorted((SAMPLE / "depth_gt").glob("*.png"))):
        write_depth_png(tmp / "pred" / gt_path.name, read_depth_file(gt_path) * (1 + 0.1 * (k + 1)))
    out = tmp / "run" / "eval_ds_test.json"
    res = run("eval", "--pred", tmp / "pred", "--gt", SAMPLE / "depth_gt", "-o", out, "-q")
    assert res.exit_code == 0, res.output
    return out


@pytest.fixture(scope="module")
def page(sample_ds, eval_file, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("page") / "report.html"
    res = run("dataset", "report", sample_ds, "-o", out, "--eval", eval_file)
    assert res.exit_code == 0, res.output
    return out


class _Tags(HTMLParser):
    """Every start tag with its attributes, and whether start and end tags balance."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack: list[str] = []
        self.errors: list[str] = []
        self.tags: list[tuple[str, dict]] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag not in VOID:
            self.errors.append(f"<{tag} /> is not a void element")

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()


def parse(path: Path) -> tuple[_Tags, ET.Element]:
    text = path.read_text(encoding="utf-8")
    tags = _Tags()
    tags.feed(text)
    tags.close()
    return tags, ET.fromstring(text)  # XHTML-compatible: a strict XML parser reads it too


def decode_data_uri(uri: str) -> np.ndarray:
    import cv2

    m = re.fullmatch(r"data:image/(png|jpeg);base64,([A-Za-z0-9+/=]+)", uri)
    assert m, uri[:60]
    img = cv2.imdecode(np.frombuffer(base64.b64decode(m.group(2)), np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return img


def text_of(el: ET.Element) -> str:
    return "".join(el.itertext())


# -- the document ----------------------------------------------------------------------------------


def test_page_is_well_formed_and_links_only_to_itself(page):
    tags, root = parse(page)
    assert tags.errors == [] and tags.stack == []
    assert root.tag == "html"
    names = [t for t, _ in tags.tags]
    for banned in ("script", "link", "iframe", "object", "embed", "base"):
        assert banned not in names
    ids = {a["id"] for _, a in tags.tags if "id" in a}
    hrefs = [a["href"] for t, a in tags.tags if "href" in a]
    assert hrefs, "the page has its section links"
    for h in hrefs:  # only the page's own sections: nothing outside it, no other file
        assert h.startswith("#") and h[1:] in ids, h
    imgs = [a for t, a in tags.tags if t == "img"]
    assert len(imgs) >= 4 + 3  # 2 plots + colour bar + one thumbnail per split (+ eval)
    for a in imgs:
        img = decode_data_uri(a["src"])  # embedded, decodable
        if "width" in a:
            assert img.shape[:2] == (int(a["height"]), int(a["width"]))
    assert not re.search(r"(src|href)\s*=\s*[\"']?\s*(https?:|//|file:)", page.read_text())


def test_one_entry_per_split_with_the_counts_of_dataset_info(page, sample_ds):
    info = dataset_info(sample_ds)
    _, root = parse(page)
    rows = [tr for tr in root.iter("tr") if tr.get("class") == "split"]
    assert [tr.get("data-split") for tr in rows] == list(info.splits) == ["test", "train", "val"]
    for tr in rows:
        cells = [text_of(td) for td in tr]
        counts = info.splits[tr.get("data-split")]
        assert [int(c.replace(",", "")) for c in cells[1:4]] == [
            counts.samples, counts.sequences, counts.with_gt,
        ]  # fmt: skip
        assert cells[4] == "lidar-64 (1)"
    text = text_of(root)
    assert f"{info.samples} in {info.sequences} sequence(s), 3 split(s)" in text
    d = info.density_percent
    assert f"min {d.min:.4g}, median {d.median:.4g}, mean {d.mean:.4g}, max {d.max:.4g}" in text
    # a thumbnail section per split, each frame once, labelled with its id
    heads = [h for h in root.iter("h3") if h.get("data-split")]
    assert [h.get("data-split") for h in heads] == ["test", "train", "val"]
    figures = [f.get("data-id") for f in root.iter("figure")]
    table, _ = read_manifest(sample_ds / "manifest.parquet")
    eval_ids = 3  # the eval section shows its worst frames again
    assert sorted(figures[: len(figures) - eval_ids]) == sorted(table.column("id").to_pylist())
    for f in root.iter("figure"):
        assert text_of(f.find("figcaption")).count(f.get("data-id")) == 1


def test_the_checks_of_verify_pass_on_an_intact_dataset(page):
    _, root = parse(page)
    checks = [tr for tr in root.iter("tr") if tr.get("class") == "check"]
    assert len(checks) == 6
    assert all(text_of(tr[1]) == "passed" for tr in checks)
    assert "3 sample(s) verified, no problem" in text_of(root)


def test_eval_rows_worst_first(page, eval_file, sample_ds):
    _, root = parse(page)
    rows = [tr for tr in root.iter("tr") if tr.get("class") == "eval-row"]
    ids = [text_of(tr[1]) for tr in rows]
    # the reference: RMSE of each frame's prediction computed here from the files (eval's
    # protocol: 1e-3 < gt < 80 m evaluated, predictions clipped to [1e-3, 80] m)
    rmse = {}
    for gt_path in sorted((SAMPLE / "depth_gt").glob("*.png")):
        gt = read_depth_file(gt_path)
        pred = np.clip(read_depth_file(eval_file.parent.parent / "pred" / gt_path.name), 1e-3, 80)
        m = (gt > 1e-3) & (gt < 80)
        rmse[gt_path.stem] = float(np.sqrt(np.mean((pred[m] - gt[m]) ** 2)))
    assert ids == sorted(rmse, key=rmse.get, reverse=True) == ["000002", "000001", "000000"]
    shown = [float(text_of(tr[3])) for tr in rows]
    assert shown == pytest.approx([rmse[i] for i in ids], abs=1e-3)
    split_of = {r.id: r.split for r in ManifestRow.from_table(read_manifest(
        sample_ds / "manifest.parquet")[0])}  # fmt: skip
    assert [text_of(tr[2]) for tr in rows] == [split_of[i] for i in ids]


def test_eval_from_a_run_folder_and_its_refusals(sample_ds, eval_file, tmp_path):
    out = tmp_path / "r.html"
    res = run("dataset", "report", sample_ds, "-o", out, "--eval", eval_file.parent,
              "--thumbnails", "0")  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "3 evaluated image(s)" in res.output and "0 thumbnail(s)" in res.output
    _, root = parse(out)
    ids = [text_of(tr[1]) for tr in root.iter("tr") if tr.get("class") == "eval-row"]
    assert ids == ["000002", "000001", "000000"]
    assert not list(root.iter("figure"))
    empty = tmp_path / "run_without_eval"
    empty.mkdir()
    res = run("dataset", "report", sample_ds, "-o", tmp_path / "e.html", "--eval", empty)
    assert res.exit_code == 1 and "sparsetools eval" in res.output
    assert len(res.output.strip().splitlines()) == 1 and not (tmp_path / "e.html").exists()
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"per_image": [{"id": "nope", "rmse": 1.0}]}))
    res = run("dataset", "report", sample_ds, "-o", tmp_path / "e.html", "--eval", other)
    assert res.exit_code == 1 and "none of its 1 evaluated image(s)" in res.output
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"per_image": [{"id": "000000", "rmse": "<b>"}]}))
    res = run("dataset", "report", sample_ds, "-o", tmp_path / "e.html", "--eval", bad)
    assert res.exit_code == 1 and "rmse is not a number" in res.output
    assert not (tmp_path / "e.html").exists()


# -- choices, escaping, resume ----------------------------------------------------------------------


def _rows(densities):
    fields = {f.name: None for f in dataclasses.fields(ManifestRow)}
    fields.update(sequence="s", frame="f", split="train", width=10, height=10, rgb_path="x.png",
                  n_sparse=0, density=0.0)  # fmt: skip
    return [
        ManifestRow(**{**fields, "id": f"f{i:02d}", "density": d}) for i, d in enumerate(densities)
    ]


def test_thumbnails_are_the_extremes_then_a_spread_each_frame_once():
    from sparsetools.pipeline.dataset.report_data import pick_thumbnails

    rows = _rows([0.5, 0.1, 0.9, 0.3, 0.7, 0.2, 0.8, 0.4, 0.6, 0.05])
    groups = pick_thumbnails(rows, 2)
    assert [t for t, _ in groups] == ["lowest density", "highest density",
                                      "spread over the split (by id)"]  # fmt: skip
    ids = [[r.id for r in g] for _, g in groups]
    assert ids[0] == ["f09", "f01"]  # 0.05, 0.1
    assert ids[1] == ["f02", "f06"]  # 0.9, 0.8: densest first
    rest = sorted({r.id for r in rows} - set(ids[0]) - set(ids[1]))
    assert ids[2] == [rest[0], rest[-1]]  # evenly spread in id order: both ends
    flat = [i for g in ids for i in g]
    assert len(flat) == len(set(flat))
    few = pick_thumbnails(rows[:5], 2)  # 5 <= 3 x 2: every frame, lowest density first
    assert [[r.density for r in g] for _, g in few] == [[0.1, 0.3, 0.5, 0.7, 0.9]]
    assert pick_thumbnails(rows, 0) == [] and pick_thumbnails([], 3) == []
    one = pick_thumbnails(rows[:1], 1)
    assert [[r.id for r in g] for _, g in one] == [["f00"]]


@pytest.fixture
def hostile_ds(tmp_path) -> Path:
    """A tiny dataset whose sequence names and source hold markup."""
    rng = np.random.default_rng(0)
    root = tmp_path / "in"
    for seq in ("a<b>&c", 'q"uote'):
        for f in range(2):
            key = f"{seq}/{f:04d}"
            write_image(root / "rgb" / f"{key}.png", rng.integers(0, 256, (16, 32, 3), np.uint8))
            d = np.where(rng.random((16, 32)) < 0.2, rng.uniform(1, 60, (16, 32)), 0)
            write_depth_png(root / "sparse" / f"{key}.png", d.astype(np.float32))
    res = run("dataset", "build", "-o", tmp_path / "ds", "--rgb", root / "rgb", "--sparse",
              root / "sparse", "--source", "<script>alert(1)</script>", "-q")  # fmt: skip
    assert res.exit_code == 0, res.output
    return tmp_path / "ds"


def test_strings_of_the_dataset_are_escaped(hostile_ds, tmp_path):
    out = tmp_path / "page.html"
    res = run("dataset", "report", hostile_ds, "-o", out)
    assert res.exit_code == 0, res.output
    text = out.read_text()
    assert "<script" not in text and "<b>&c" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text
    tags, root = parse(out)
    assert tags.errors == [] and "script" not in [t for t, _ in tags.tags]
    cells = " ".join(text_of(td) for td in root.iter("td"))
    assert "a<b>&c (2)" in cells and 'q"uote (2)' in cells  # shown as written
    assert "<script>alert(1)</script> (4)" in cells


def test_resume_refusals_and_containment(sample_ds, tmp_path):
    out_dir = tmp_path / "o"
    out = out_dir / "report.html"
    assert run("dataset", "report", sample_ds, "-o", out, "--thumbnails", "1").exit_code == 0
    before = (out.stat().st_mtime_ns, out.read_bytes())
    res = run("dataset", "report", sample_ds, "-o", out, "--thumbnails", "1", "--json")
    assert res.exit_code == 0 and json.loads(res.output)["status"] == "up to date"
    assert (out.stat().st_mtime_ns, out.read_bytes()) == before
    res = run("dataset", "report", sample_ds, "-o", out, "--thumbnails", "2")
    assert res.exit_code == 1 and "--thumbnails 1, not 2" in res.output
    assert out.read_bytes() == before[1]
    res = run("dataset", "report", sample_ds, "-o", out, "--thumbnails", "0", "--overwrite")
    assert res.exit_code == 0 and b"<figure" in before[1] and b"<figure" not in out.read_bytes()
    # only the page and its record, nothing else, and no temporary file left
    assert sorted(p.name for p in out_dir.iterdir()) == [".sparsetools", "report.html"]
    mine = tmp_path / "mine.html"
    mine.write_text("my notes")
    res = run("dataset", "report", sample_ds, "-o", mine)
    assert res.exit_code == 1 and "was not written by this command" in res.output
    assert mine.read_text() == "my notes"
    res = run("dataset", "report", sample_ds, "-o", tmp_path / "page.txt")
    assert res.exit_code != 0 and "written as .html" in res.output
    assert not (tmp_path / "page.txt").exists()


def test_without_matplotlib_one_line_naming_the_extra(sample_ds, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    res = CliRunner().invoke(cli, ["dataset", "report", str(sample_ds), "-o",
                                   str(tmp_path / "r.html")])  # fmt: skip
    assert res.exit_code == 1
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and "pip install 'sparsetools[viz]'" in lines[0], res.output
    assert not (tmp_path / "r.html").exists()


def test_a_damaged_dataset_gets_its_page_with_the_problem_under_its_check(sample_ds, tmp_path):
    ds = tmp_path / "ds"
    shutil.copytree(sample_ds, ds)
    table, _ = read_manifest(ds / "manifest.parquet")
    row = ManifestRow.from_table(table)[0]
    (ds / row.rgb_path).unlink()
    out = tmp_path / "r.html"
    res = run("dataset", "report", ds, "-o", out)
    assert res.exit_code == 0 and "1 problem(s)" in res.output, res.output
    _, root = parse(out)
    checks = {
        text_of(tr[0]): text_of(tr[1]) for tr in root.iter("tr") if tr.get("class") == "check"
    }
    assert checks["every file inside the dataset, present and readable"] == "1 problem(s)"
    assert sum(v == "passed" for v in checks.values()) == 5
    assert f"{row.id}: {row.rgb_path} is missing" in text_of(root)
    fig = next(f for f in root.iter("figure") if f.get("data-id") == row.id)
    assert fig.find("img") is None and "cannot be drawn" in text_of(fig)


def test_matplotlib_is_imported_only_to_draw():
    """The command line and the report module load without matplotlib (the optional extra)."""
    import sys

    code = ("import sys, sparsetools.cli.main, sparsetools.cli.dataset, "
            "sparsetools.pipeline.dataset.report; print('matplotlib' in sys.modules)")  # fmt: skip
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1] / "src")})  # fmt: skip
    assert r.returncode == 0 and r.stdout.strip() == "False", r.stderr[-2000:]


# -- the demo's pipeline links the page -------------------------------------------------------------


def test_pipeline_steps_link_the_pages_they_write(tmp_path):
    from sparsetools.errors import FormatError
    from sparsetools.pipeline.workflow import load_workflow, run_workflow

    cfg = tmp_path / "c.yaml"
    cfg.write_text("steps:\n  - name: page\n    run: dataset report x -o ${out}/p.html\n"
                   "    links: ['${out}/p.html', '${out}/never.html']\n")  # fmt: skip
    out = tmp_path / "out"
    wf = load_workflow(cfg, out_dir=out)
    assert wf.steps[0].links == [f"{out}/p.html", f"{out}/never.html"]

    def fake(args):
        (out / "p.html").write_text("<p>x</p>")
        return 0, "written\n", ""

    run_workflow(wf, out, run_command=fake, echo=lambda *_: None)
    report = (out / "report.md").read_text()
    assert "[p.html](p.html)" in report and "never.html" not in report  # only what exists
    cfg.write_text("steps:\n  - run: info\n    links: [1]\n")
    with pytest.raises(FormatError, match="links: a list of paths"):
        load_workflow(cfg, out_dir=out)


# -- in a real browser ------------------------------------------------------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


def _screenshot(page: Path, tmp_path: Path, size: tuple[int, int]) -> np.ndarray:
    """Headless Chromium's screenshot of ``page`` at ``size`` (width, height), as BGR."""
    import cv2

    shot = tmp_path / f"{page.stem}.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           "--no-first-run", "--disable-extensions", f"--user-data-dir={tmp_path / 'profile'}",
           f"--window-size={size[0]},{size[1]}", f"--screenshot={shot}",
           page.resolve().as_uri()]  # fmt: skip
    env = {**os.environ, "HOME": str(tmp_path)}
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0 and shot.is_file(), r.stderr[-2000:]
    img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    assert img is not None
    return img


def _saturated_share(img: np.ndarray) -> float:
    """Share of strongly coloured pixels: the plots' curves and the thumbnails' depth colours
    (the page's text and tables are black, grey and link blue on white)."""
    import cv2

    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    return float(((hsv[..., 1] > 120) & (hsv[..., 2] > 80)).mean())


@pytest.mark.skipif(
    CHROMIUM is None,
    reason="Debian's chromium is not installed (.ci/run installs it: apt-get install chromium)",
)
def test_chromium_renders_the_page(page, tmp_path):
    size = (1280, 2000)
    img = _screenshot(page, tmp_path, size)
    assert img.shape == (size[1], size[0], 3)
    assert float(img.std()) > 20  # not a blank page
    # The pictures rendered: the histograms' coloured curves and the first thumbnails are on
    # screen (about 1 % of the pixels; the same page with its pictures broken has < 0.1 %).
    assert _saturated_share(img) > 0.002, _saturated_share(img)
    broken = tmp_path / "broken.html"
    broken.write_text(re.sub(r'src="data:[^"]*"', 'src="missing.png"', page.read_text()))
    assert _saturated_share(_screenshot(broken, tmp_path, size)) < 0.002  # the check is live
    # and every picture of the page decodes (what the browser could not draw, cv2 cannot)
    tags, _ = parse(page)
    for t, a in tags.tags:
        if t == "img":
            decode_data_uri(a["src"])
