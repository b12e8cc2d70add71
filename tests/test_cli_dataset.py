"""``sparsetools dataset build / info / verify`` from the command line."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.dataset import MANIFEST_NAME
from sparsetools.io.dataset_reader import DatasetReader
from sparsetools.io.image import write_depth_png, write_image

W, H = 32, 16


def tree_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and ".sparsetools" not in p.parts:  # the run record holds timings
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


@pytest.fixture
def inputs(tmp_path):
    rng = np.random.default_rng(0)
    root = tmp_path / "in"
    for seq in ("s1", "s2", "s3", "s4"):
        for f in range(2):
            key = f"{seq}/{f:04d}"
            write_image(
                root / "rgb" / f"{key}.png", rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            )
            d = np.where(rng.random((H, W)) < 0.2, rng.uniform(1, 60, (H, W)), 0).astype(np.float32)
            write_depth_png(root / "sparse" / f"{key}.png", d)
            write_depth_png(root / "gt" / f"{key}.png", rng.uniform(1, 60, (H, W)))
    (root / "calib.json").write_text(
        json.dumps(
            {
                "K": [[30.0, 0, 15.5], [0, 30.0, 7.5], [0, 0, 1]],
                "T_cam_from_sensor": np.eye(4).tolist(),
            }
        )
    )
    return root


def run(args):
    runner = CliRunner()
    return runner.invoke(cli, [str(a) for a in args], catch_exceptions=False)


def build_args(inputs, out, *extra):
    return [
        "dataset",
        "build",
        "-o",
        out,
        "--rgb",
        inputs / "rgb",
        "--sparse",
        inputs / "sparse",
        "--gt",
        inputs / "gt",
        "--calib",
        inputs / "calib.json",
        *extra,
    ]


def test_build_info_verify(inputs, tmp_path):
    out = tmp_path / "ds"
    before = tree_hash(inputs)
    settings = ("--splits", "0.5,0.25,0.25", "--seed", "3", "--source", "lidar-64")
    res = run(build_args(inputs, out, "--json", *settings, "--params", '{"beams": 64}'))
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["samples"] == 8 and summary["processed"] == 8 and summary["sequences"] == 4
    assert summary["splits"] == {"test": 2, "train": 4, "val": 2}
    assert set(summary["stage_seconds"]) >= {
        "t_hash",
        "t_encode",
        "t_write",
        "t_stage",
        "t_finalize",
    }
    assert tree_hash(inputs) == before  # inputs untouched
    row = DatasetReader(out).row("s1/0000")
    assert row.source == "lidar-64" and row.fx == 30.0
    assert json.loads(row.generation_params)["params"] == {"beams": 64}

    res = run(["dataset", "info", out])
    assert res.exit_code == 0, res.output
    assert "schema version" in res.stdout and "train" in res.stdout and f"{W}x{H} (8)" in res.stdout
    info = json.loads(run(["dataset", "info", out, "--json"]).stdout)
    assert info["schema_version"] == 2 and info["splits"]["train"]["samples"] == 4
    assert info["with_intrinsics"] == 8 and info["sources"] == {"lidar-64": 8}
    assert info["bytes"]["rgb"] > 0 and info["density_percent"]["max"] <= 100

    res = run(["dataset", "verify", out])
    assert res.exit_code == 0 and "no problem" in res.stdout

    # a rerun resumes: nothing to do; other settings are refused, naming the first that differs
    res = run(build_args(inputs, out, "--json", *settings, "--params", '{"beams": 64}'))
    assert res.exit_code == 0 and json.loads(res.stdout)["skipped_existing"] == 8
    res = run(build_args(inputs, out, *settings))
    assert res.exit_code == 1 and "made with --params" in res.stderr


def test_text_summary_and_workers(inputs, tmp_path):
    res = run(build_args(inputs, tmp_path / "ds", "--workers", "2", "--sparse-format", "parquet"))
    assert res.exit_code == 0, res.output
    assert "samples" in res.stdout and "splits" in res.stdout and "train" in res.stdout
    # one line per total, no internal timings (those are in --json's stage_seconds)
    lines = res.stdout.splitlines()
    assert lines[0] == f"dataset written to {tmp_path / 'ds'}"
    assert not [ln for ln in lines if re.search(r"\bt_[a-z]+|stage", ln)], res.stdout
    assert [ln.split()[0] for ln in lines[1:]].count("splits") == 1
    assert not list((tmp_path / "ds" / "sparse").rglob("*.png"))


def test_verify_reports_problems_and_exits_1(inputs, tmp_path):
    out = tmp_path / "ds"
    assert run(build_args(inputs, out)).exit_code == 0
    png = out / "sparse" / "s2" / "0001.png"
    png.write_bytes(png.read_bytes()[:40])
    res = run(["dataset", "verify", out])
    assert res.exit_code == 1
    assert "s2/0001" in res.stdout and "problem:" in res.stdout
    assert "Traceback" not in res.output and res.stderr.count("\n") == 1
    report = json.loads(run(["dataset", "verify", out, "--json"]).stdout)
    assert len(report["problems"]) >= 1


def test_usage_errors_exit_2(inputs, tmp_path):
    out = tmp_path / "ds"
    for extra in (
        ["--splits", "0.5,0.6"],
        ["--splits", "a,b,c"],
        ["--sequence-from", "folder"],
        ["--sequence-from", "regex:("],
        ["--params", "[1, 2]"],
        ["--split-file", tmp_path / "missing.txt"],
    ):
        res = run(build_args(inputs, out, *extra))
        assert res.exit_code == 2, (extra, res.output)
        assert "Traceback" not in res.output
    (tmp_path / "train.txt").write_text("s1/0000\n")
    res = run(
        build_args(inputs, out, "--splits", "0.5,0.5", "--split-file", tmp_path / "train.txt")
    )
    assert res.exit_code == 2
    res = run(
        ["dataset", "build", "-o", out, "--rgb", tmp_path / "nope", "--sparse", inputs / "sparse"]
    )
    assert res.exit_code == 2
    assert not out.exists()


def test_library_errors_exit_1_without_partial_output(inputs, tmp_path):
    out = tmp_path / "ds"
    write_depth_png(inputs / "sparse" / "s1" / "0001.png", np.ones((H + 1, W)))
    before = tree_hash(inputs)
    res = run(build_args(inputs, out))
    assert res.exit_code == 1
    assert "Traceback" not in res.output
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("Error:") and "s1/0001" in err[0]
    assert not (out / MANIFEST_NAME).exists()
    assert not list(out.rglob(".tmp-sparsetools-*"))
    assert tree_hash(inputs) == before
    res = run(["dataset", "info", tmp_path])
    assert res.exit_code == 1 and "no such manifest" in res.stderr


def test_split_file_option_and_link(inputs, tmp_path):
    (tmp_path / "train.txt").write_text("s1/0000\ns1/0001\ns2/0000\n")
    (tmp_path / "held.txt").write_text("s3 1\n")
    out = tmp_path / "ds"
    res = run(
        build_args(
            inputs,
            out,
            "--split-file",
            tmp_path / "train.txt",
            "--split-file",
            f"holdout={tmp_path / 'held.txt'}",
            "--link",
            "--json",
        )
    )
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["splits"] == {"holdout": 1, "train": 3}
    assert summary["unmatched"]["not_in_split_files"] == 4
    src = inputs / "rgb" / "s1" / "0000.png"
    # --link: reflink where possible, else a copy; never the input's own inode
    assert (out / "rgb" / "s1" / "0000.png").stat().st_ino != src.stat().st_ino
    assert (out / "rgb" / "s1" / "0000.png").read_bytes() == src.read_bytes()
    assert DatasetReader(out).split("holdout").ids == ["s3/0001"]


def test_verify_reports_inputs_changed_since_the_build(inputs, tmp_path):
    out = tmp_path / "ds"
    res = run(build_args(inputs, out))
    assert res.exit_code == 0, res.output
    assert run(["dataset", "verify", out]).exit_code == 0
    sparse = sorted((inputs / "sparse").rglob("*.png"))[0]
    sparse.write_bytes(sparse.read_bytes()[:-1] + b"\x00")  # the user's input changed
    res = run(["dataset", "verify", out])
    assert res.exit_code == 1 and "changed since the build" in res.stdout
    assert sparse.name.split(".")[0] in res.stdout
    # rebuilding makes the dataset current again
    assert run(build_args(inputs, out)).exit_code == 0
    assert run(["dataset", "verify", out]).exit_code == 0


# -- the 0.2 spellings: hidden aliases that work for one release, with one warning --------------------
def _deprecation_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "deprecated" in line]


def test_build_split_is_the_old_spelling_of_splits(inputs, tmp_path):
    new = run(build_args(inputs, tmp_path / "new", "--splits", "0.5,0.5", "--seed", "1", "--json"))
    old = run(build_args(inputs, tmp_path / "old", "--split", "0.5,0.5", "--seed", "1", "--json"))
    assert new.exit_code == 0 and old.exit_code == 0, old.output
    assert _deprecation_lines(new.stderr) == []
    assert _deprecation_lines(old.stderr) == [
        "WARNING: deprecated: --split 0.5,0.5 is now --splits 0.5,0.5 (--split NAME picks an "
        "official split; its fraction spelling goes in 0.4)"
    ]
    drop = ("seconds", "stage_seconds", "output")
    summary = {k: v for k, v in json.loads(old.stdout).items() if k not in drop}
    assert summary == {k: v for k, v in json.loads(new.stdout).items() if k not in drop}
    assert tree_hash(tmp_path / "old") == tree_hash(tmp_path / "new")
    both = run(build_args(inputs, tmp_path / "both", "--split", "0.5,0.5", "--splits", "0.5,0.5"))
    assert both.exit_code == 2 and "give --splits only" in both.stderr
    assert not (tmp_path / "both").exists()
    bad = run(build_args(inputs, tmp_path / "bad", "--split", "0.5,abc"))  # read as --splits reads
    assert bad.exit_code == 2 and "split fractions as numbers" in bad.stderr


def test_verify_workers_is_the_old_spelling_of_threads(inputs, tmp_path):
    out = tmp_path / "ds"
    assert run(build_args(inputs, out)).exit_code == 0
    new = run(["dataset", "verify", out, "--threads", "2", "--json"])
    old = run(["dataset", "verify", out, "--workers", "2", "--json"])
    assert new.exit_code == old.exit_code == 0 and new.stdout == old.stdout
    assert _deprecation_lines(new.stderr) == []
    assert _deprecation_lines(old.stderr) == [
        "WARNING: deprecated: --workers is now --threads (the old spelling goes in 0.4)"
    ]
    both = run(["dataset", "verify", out, "--workers", "2", "--threads", "2"])
    assert both.exit_code == 2 and "give --threads only" in both.stderr
    assert run(["dataset", "verify", out, "--workers", "0"]).exit_code == 2


@pytest.mark.parametrize(
    "command, function",
    [("kitti-raw", "build_kitti_raw_dataset"), ("nuscenes", "build_nuscenes_dataset")],
)
def test_route_split_is_the_old_spelling_of_splits(command, function, monkeypatch, tmp_path):
    """dataset kitti-raw / nuscenes pass --splits (or the old --split) on as the fractions."""
    from sparsetools.pipeline import RunSummary
    from sparsetools.pipeline.dataset import roots

    calls = []

    def fake(root, out_dir, **kw):
        calls.append(kw["split"])
        return RunSummary(command="dataset build", output=out_dir)

    monkeypatch.setattr(roots, function, fake)
    base = ["dataset", command, tmp_path, "-o", tmp_path / "ds", "--json"]
    new = run([*base, "--splits", "0.6,0.2,0.2"])
    old = run([*base, "--split", "0.6,0.2,0.2"])
    assert new.exit_code == old.exit_code == 0, old.output
    assert calls == [{"train": 0.6, "val": 0.2, "test": 0.2}] * 2
    assert len(_deprecation_lines(old.stderr)) == 1 and not _deprecation_lines(new.stderr)
    both = run([*base, "--split", "0.6,0.4", "--splits", "0.6,0.4"])
    assert both.exit_code == 2 and len(calls) == 2


def test_nuscenes_crop_is_wxh_left_top(monkeypatch, tmp_path):
    """--crop 800x350+0+100: 800x350 pixels at column 0, row 100 (the old 100,0,350,800)."""
    from sparsetools.pipeline import RunSummary
    from sparsetools.pipeline.dataset import roots

    crops = []

    def fake(root, out_dir, **kw):
        crops.append(kw["crop"])
        return RunSummary(command="dataset build", output=out_dir)

    monkeypatch.setattr(roots, "build_nuscenes_dataset", fake)
    base = ["dataset", "nuscenes", tmp_path, "-o", tmp_path / "ds", "--resize", "0.5"]
    new = run([*base, "--crop", "800x350+0+100"])
    old = run([*base, "--crop", "100,0,350,800"])
    assert new.exit_code == old.exit_code == 0, old.output
    assert crops == [(100, 0, 350, 800)] * 2  # (top, left, height, width)
    assert not _deprecation_lines(new.stderr)
    assert _deprecation_lines(old.stderr) == [
        "WARNING: deprecated: --crop 100,0,350,800 (TOP,LEFT,H,W) is the old syntax: write "
        "--crop 800x350+0+100 (WxH+LEFT+TOP)"
    ]


def test_info_counts_what_is_on_disk(inputs, tmp_path):
    """The size of a dataset is what its folder holds: the files the manifest names, what a
    route staged in .sources/ (kept for its reruns) and the rest (records), each once."""
    out = tmp_path / "ds"
    assert run(build_args(inputs, out)).exit_code == 0
    staged = out / ".sources" / "images" / "000000.png"
    staged.parent.mkdir(parents=True)
    staged.write_bytes(b"x" * 5000)
    (out / "rgb" / "link.png").symlink_to(staged)  # a link is not a second copy
    info = json.loads(run(["dataset", "info", out, "--json"]).stdout)
    on_disk = sum(p.stat().st_size for p in out.rglob("*") if p.is_file() and not p.is_symlink())
    assert info["bytes"]["sources"] == 5000 and info["bytes"]["other"] > 0
    assert info["total_bytes"] == on_disk == sum(info["bytes"].values())
    assert "sources 4.9 KB" in run(["dataset", "info", out]).stdout


@pytest.mark.real
def test_a_route_refusal_names_the_option_typed(real_dir, tmp_path):
    """The nuScenes route records its options in the build's ``params``: a refusal names
    ``--sweeps``, as typed, not ``--params sweeps``."""
    from _nuscenes_tree import build_tree

    build_tree(real_dir, tmp_path / "nus")
    out = tmp_path / "ds"
    assert run(["-q", "dataset", "nuscenes", tmp_path / "nus", "-o", out]).exit_code == 0
    for option, message in (
        (["--sweeps", "3"], "made with --sweeps 5, not 3"),
        (["--gt-sensor", "none"], "made with --gt-sensor LIDAR_TOP, not none"),
        (["--jbf"], "made with --jbf off, not on"),
    ):
        r = run(["-q", "dataset", "nuscenes", tmp_path / "nus", "-o", out, *option])
        assert r.exit_code == 1 and message in r.stderr, r.stderr
