"""The resume rule, command by command: between two runs into the same -o, a changed setting
is refused (naming it) and a changed input file recomputes exactly the frames that read it:
their outputs then hold the bytes a fresh run gives, and the other frames' outputs are left
as they were (same bytes, not rewritten)."""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from robustness.corpus_builder import tree_digest
from sparsetools.cli.main import cli
from sparsetools.io.provenance import RECORD_DIR

SYNTH = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"


def run(*args):
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    return r


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A private copy of the sample data (its files are changed by the tests)."""
    root = tmp_path_factory.mktemp("data")
    for name in ("velodyne", "calib", "image_2", "depth_gt", "calib_radar"):
        shutil.copytree(SYNTH / name, root / name)
    (root / "radar").mkdir()
    for i in range(3):
        shutil.copy(SYNTH / "radar" / f"{i:06d}.pcd", root / "radar" / f"{i:06d}.pcd")
    seafloor = sorted((SYNTH / "underwater" / "seafloor").iterdir())  # 40 frames: 2 segments
    (root / "seafloor").mkdir()
    for p in seafloor:
        shutil.copy(p, root / "seafloor" / p.name)
    shutil.copytree(SYNTH / "underwater" / "water", root / "water")
    # sparse depth maps for jbf-expand and dataset build
    assert run("project", root / "velodyne", "--calib", root / "calib", "--image-size",
               "1242x375", "-o", root / "lidar").exit_code == 0  # fmt: skip
    assert run("project", root / "radar", "--calib", root / "calib_radar", "-o",
               root / "radar_depth").exit_code == 0  # fmt: skip
    return root


def _change_image(path: Path) -> None:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    img = img.copy()
    img[: img.shape[0] // 2] = 255 - img[: img.shape[0] // 2]
    cv2.imwrite(str(path), img)


def _change_cloud(path: Path) -> None:
    """Drop the last 100 points: another file, the same lasers (the rings beams selects are
    measured on far points of several frames and stay the same)."""
    pts = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    pts[:-100].tofile(path)


def _change_depth(path: Path) -> None:
    import cv2

    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    d = d.copy()
    d[d > 0] = np.minimum(d[d > 0].astype(np.int64) + 256, 65535).astype(np.uint16)
    cv2.imwrite(str(path), d)


@dataclass
class Case:
    name: str
    args: callable  # (data, out) -> list of arguments
    setting: tuple[str, str]  # an option and a value other than the first run's
    message: str  # what the refusal names
    change: callable  # (data) -> None: change one input file
    recomputed: int = 1


CASES = [
    Case(
        "project",
        lambda d, o: [
            "project",
            d / "velodyne",
            "--calib",
            d / "calib",
            "--image-size",
            "1242x375",
            "-o",
            o,
        ],
        ("--max-depth", "20"),
        "made with --max-depth none, not 20",
        lambda d: _change_cloud(d / "velodyne" / "000001.bin"),
    ),
    Case(
        "beams",
        lambda d, o: ["beams", d / "velodyne", "--n", "4", "-o", o],
        ("--far-range", "25"),
        "made with --far-range 20, not 25",
        lambda d: _change_cloud(d / "velodyne" / "000002.bin"),
    ),
    Case(
        "jbf-expand",
        lambda d, o: [
            "jbf-expand",
            d / "radar_depth",
            "--image",
            d / "image_2",
            "--calib",
            d / "calib_radar",
            "-o",
            o,
        ],
        ("--sigma-s", "12"),
        "made with --sigma-s 25, not 12",
        lambda d: _change_image(d / "image_2" / "000001.png"),
    ),
    Case(
        "lowlight-synth",
        lambda d, o: ["lowlight-synth", d / "image_2", "-o", o, "--seed", "3"],
        ("--seed", "4"),
        "made with --seed 3, not 4",
        lambda d: _change_image(d / "image_2" / "000002.png"),
    ),
    Case(
        "equalize",
        lambda d, o: ["equalize", d / "image_2", "-o", o, "--reference-frame", "000000"],
        ("--clip", "0.008"),
        "made with --clip 0.004, not 0.008",
        lambda d: _change_image(d / "image_2" / "000001.png"),
    ),
    Case(
        "underwater",
        lambda d, o: [
            "underwater",
            d / "seafloor",
            "--water",
            d / "water",
            "-o",
            o,
            "--median-window",
            "3",
            "--workers",
            "1",
        ],
        ("--eps", "0.01"),
        "made with --eps 0.001, not 0.01",
        # the last frame: only the segment streaming it (A_ref comes from the first window)
        lambda d: _change_image(sorted((d / "seafloor").iterdir())[-1]),
    ),
    Case(
        "dataset build",
        lambda d, o: [
            "dataset",
            "build",
            "-o",
            o,
            "--rgb",
            d / "image_2",
            "--sparse",
            d / "lidar",
            "--gt",
            d / "depth_gt",
            "--calib",
            d / "calib",
        ],
        ("--source", "radar"),
        "made with --source lidar, not radar",
        lambda d: _change_depth(d / "lidar" / "000001.png"),
    ),
    Case(
        "defocus-synth",
        lambda d, o: [
            "defocus-synth",
            d / "image_2",
            "--depth",
            d / "depth_gt",
            "--missing-depth",
            "far",
            "-o",
            o,
        ],
        ("--focus-distance", "2"),
        "made with --focus-distance 0.7,0.7, not 2,2",
        lambda d: _change_depth(d / "depth_gt" / "000002.png"),
    ),
    Case(
        "dark-channel",
        lambda d, o: ["dark-channel", d / "image_2", "-o", o],
        ("--patch-size", "7"),
        "made with --patch-size 15, not 7",
        lambda d: _change_image(d / "image_2" / "000000.png"),
    ),
    Case(
        "densify",
        lambda d, o: ["densify", d / "lidar", "-o", o],
        ("--variant", "bilateral"),
        "made with --variant gaussian, not bilateral",
        lambda d: _change_depth(d / "lidar" / "000002.png"),
    ),
    Case(
        "accumulate",
        lambda d, o: [
            "accumulate",
            d / "velodyne",
            "--calib",
            d / "calib",
            "--image-size",
            "1242x375",
            "--icp",
            "--neighbours",
            "1",
            "-o",
            o,
        ],
        ("--neighbours", "2"),
        "made with --neighbours 1, not 2",
        # frames 000000 and 000001 hold scan 000000 in their window (000002's is 1..2)
        lambda d: _change_cloud(d / "velodyne" / "000000.bin"),
        recomputed=2,
    ),
]


def _summary(result) -> dict:
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def _records(out: Path) -> dict[str, dict]:
    """The folder's frame records by frame id."""
    lines = (out / RECORD_DIR / "frames.jsonl").read_text().splitlines()
    return {rec["key"]: rec for rec in map(json.loads, lines)}


def _files(out: Path) -> dict[str, tuple[bytes, int]]:
    """Relative path -> (bytes, mtime in ns) of every file (the record aside)."""
    return {
        p.relative_to(out).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in out.rglob("*")
        if p.is_file() and RECORD_DIR not in p.relative_to(out).parts
    }


#: What a dataset build merges (the manifest and the Parquet parts of the points).
PARTS = re.compile(r"^(manifest\.parquet|sparse/part-\d+\.parquet)$")


def _without_parts(digests: dict) -> dict:
    return {k: v for k, v in digests.items() if not PARTS.match(k)}


def _dataset_content(ds: Path) -> tuple[dict, dict, dict]:
    """A dataset's manifest rows (but where their points are stored), its metadata and each
    sample's sparse points."""
    from sparsetools.io.dataset import read_manifest
    from sparsetools.io.dataset_parts import part_rows, read_sparse_part

    table, info = read_manifest(ds / "manifest.parquet")
    rows = {
        r["id"]: {k: v for k, v in r.items() if k not in ("sparse_parquet", "sparse_row")}
        for r in table.to_pylist()
    }
    points = {}
    for part in sorted((ds / "sparse").glob("part-*.parquet")):
        for fid, u, v, d, h, w in part_rows(read_sparse_part(part)):
            assert fid not in points, f"{fid} in two parts"
            points[fid] = (u.tobytes(), v.tobytes(), d.tobytes(), h, w)
    return rows, info, points


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_changed_setting_refused_changed_input_recomputed(case, data, tmp_path):
    out = tmp_path / "out"
    args = case.args(data, out)
    first = _summary(run(*args, "--json"))
    tasks = first.get("segments", first["frames"])  # underwater: a task is a segment of frames
    assert first["processed"] == tasks and first["failed"] == 0

    again = _summary(run(*args, "--json"))
    assert again["processed"] == 0 and again["skipped_existing"] == tasks

    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    refused = run(*args, *case.setting)
    assert refused.exit_code == 1
    lines = refused.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and "Traceback" not in refused.output
    assert case.message in lines[0] and "use --overwrite or another -o" in lines[0]
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before

    files, records = _files(out), _records(out)
    case.change(data)
    redo = _summary(run(*args, "--json"))
    assert redo["recomputed"] == case.recomputed and redo["processed"] == case.recomputed
    assert redo["skipped_existing"] == tasks - case.recomputed

    # the frames whose record changed are exactly the recomputed ones; the others' outputs
    # were not rewritten
    now, records_now = _files(out), _records(out)
    assert records_now.keys() == records.keys()
    changed = [k for k in records if records_now[k] != records[k]]
    assert len(changed) == case.recomputed, changed
    for key, rec in records.items():
        if key not in changed:
            for rel in rec["outputs"].values():  # (dataset build: staged records merged, gone)
                assert now.get(rel) == files.get(rel), f"{rel} of the up-to-date {key} changed"
    # ... and the folder holds the bytes of a fresh run on today's inputs (records included)
    fresh = tmp_path / "fresh"
    assert _summary(run(*case.args(data, fresh), "--json"))["failed"] == 0
    if case.name == "dataset build":
        # an appended dataset keeps its points in more parts than a fresh build (the
        # rebuilt frame's old part is rewritten without it): the same rows and points
        assert _dataset_content(out) == _dataset_content(fresh)
        r = run("dataset", "verify", out)
        assert r.exit_code == 0, r.output
    assert _without_parts(tree_digest(out)) == _without_parts(tree_digest(fresh))


def test_underwater_summary_names_what_it_counts(data, tmp_path):
    """A task of underwater is a segment of frames: its summary counts both, by name."""
    args = ["underwater", data / "seafloor", "--water", data / "water", "-o", tmp_path / "uw",
            "--median-window", "3"]  # fmt: skip
    s = _summary(run(*args, "--json"))
    assert (s["frames"], s["frames_processed"], s["frames_skipped_existing"]) == (40, 40, 0)
    assert (s["segments"], s["segments_processed"], s["segments_skipped_existing"]) == (2, 2, 0)
    assert s["processed"] == s["segments_processed"]  # what every command's JSON counts: tasks
    text = run(*args).stdout.splitlines()
    rows = dict(ln.rsplit(None, 1) for ln in text[1:] if not ln.startswith(("a ref", "output")))
    assert rows["frames"] == "40" and rows["frames skipped existing"] == "40"
    assert rows["segments"] == "2" and rows["segments skipped existing"] == "2"
    assert "processed" not in rows and "skipped existing" not in rows  # says what it counts
