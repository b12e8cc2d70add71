"""`sparsetools synth-scene` command: generation, --check reproducibility, bad arguments."""

from __future__ import annotations

import json

from click.testing import CliRunner

from sparsetools.cli.main import cli

SMALL = ["--frames", "1", "--image-size", "64x24", "--underwater-frames", "4", "--seed", "5"]


def test_generate_then_check_passes_and_detects_a_change(tmp_path):
    runner = CliRunner()
    r = runner.invoke(cli, ["synth-scene", "-o", str(tmp_path / "a"), *SMALL, "--json"])
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "b"), "--check", str(tmp_path / "a")]
    )
    assert r.exit_code == 0, r.output
    assert "different  0" in r.output
    (tmp_path / "a" / "velodyne" / "000000.bin").write_bytes(b"\0" * 16)
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "c"), "--check", str(tmp_path / "a")]
    )
    assert r.exit_code == 1
    assert "velodyne/000000.bin" in r.stderr and "Traceback" not in r.output


def test_refuses_to_write_into_a_non_empty_folder(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "keep.txt").write_text("mine")
    r = CliRunner().invoke(cli, ["synth-scene", "-o", str(tmp_path / "a"), *SMALL])
    assert r.exit_code == 1 and "overwrite" in r.stderr
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["keep.txt"]


def test_rerun_is_a_no_op_and_other_options_are_refused(tmp_path):
    runner = CliRunner()
    out = tmp_path / "a"
    assert runner.invoke(cli, ["synth-scene", "-o", str(out), *SMALL]).exit_code == 0
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    r = runner.invoke(cli, ["synth-scene", "-o", str(out), *SMALL, "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["up_to_date"] is True
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before
    r = runner.invoke(cli, ["synth-scene", "-o", str(out), *SMALL[:-1], "6"])
    assert r.exit_code == 1 and "made with --seed 5, not 6" in r.stderr
    # a file of the scene lost: regenerated (the folder is the command's own)
    (out / "velodyne" / "000000.bin").unlink()
    r = runner.invoke(cli, ["synth-scene", "-o", str(out), *SMALL, "--json"])
    assert r.exit_code == 0 and "up_to_date" not in json.loads(r.stdout)
    assert (out / "velodyne" / "000000.bin").is_file()


def test_bad_sizes_are_usage_errors(tmp_path):
    r = CliRunner().invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "a"), "--image-size", "64by24"]
    )
    assert r.exit_code == 2 and "WxH" in r.stderr
    r = CliRunner().invoke(cli, ["synth-scene", "-o", str(tmp_path / "a"), "--frames", "0"])
    assert r.exit_code == 2


def test_stem_prefix_names_files_and_survives_check(tmp_path):
    runner = CliRunner()
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "a"), *SMALL, "--stem-prefix", "s7_"]
    )
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "a" / "image_2").iterdir()) == ["s7_000000.png"]
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "b"), "--check", str(tmp_path / "a")]
    )
    assert r.exit_code == 0, r.output
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "c"), *SMALL, "--stem-prefix", "../x"]
    )
    assert r.exit_code == 1 and "stem prefix" in r.stderr


VIDEO = ["--video", "--sequences", "2", "--frames", "2", "--image-size", "64x24", "--seed", "1"]


def test_video_mode_writes_sequences_and_check_reproduces_them(tmp_path):
    runner = CliRunner()
    r = runner.invoke(cli, ["synth-scene", "-o", str(tmp_path / "v"), *VIDEO, "--json"])
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["sequences"] == ["seq_0000", "seq_0001"] and summary["frames"] == 2
    for seq in ("seq_0000", "seq_0001"):
        root = tmp_path / "v" / seq
        assert sorted(p.name for p in (root / "image_2").iterdir()) == [
            "0000000000.png",
            "0000000001.png",
        ]
        assert len((root / "poses.txt").read_text().splitlines()) == 2
        assert (root / "moving_mask" / "0000000001.png").is_file()
    # No single-frame outputs in video mode.
    assert not (tmp_path / "v" / "underwater").exists() and not (tmp_path / "v" / "radar").exists()
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "w"), "--check", str(tmp_path / "v")]
    )
    assert r.exit_code == 0, r.output
    assert "different  0" in r.output
    (tmp_path / "v" / "seq_0001" / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "x"), "--check", str(tmp_path / "v")]
    )
    assert r.exit_code == 1 and "seq_0001/poses.txt" in r.stderr


def test_video_options_need_video_mode_and_vice_versa(tmp_path):
    runner = CliRunner()
    r = runner.invoke(cli, ["synth-scene", "-o", str(tmp_path / "a"), "--sequences", "2"])
    assert r.exit_code == 2 and "--sequences" in r.stderr and "without --video" in r.stderr
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "a"), "--video", "--stem-prefix", "s_"]
    )
    assert r.exit_code == 2 and "--stem-prefix" in r.stderr
    r = runner.invoke(
        cli, ["synth-scene", "-o", str(tmp_path / "a"), "--video", "--antialias", "9"]
    )
    assert r.exit_code == 2
    assert not (tmp_path / "a").exists()


def test_the_old_positional_output_still_works_and_warns_once(tmp_path):
    """``synth-scene OUT`` (0.2.0) is ``synth-scene -o OUT``: the same folder, one warning;
    both forms at once are a usage error."""
    runner = CliRunner()
    new = runner.invoke(cli, ["synth-scene", "-o", str(tmp_path / "new"), *SMALL])
    old = runner.invoke(cli, ["synth-scene", str(tmp_path / "old"), *SMALL])
    assert new.exit_code == 0 and old.exit_code == 0, old.output
    assert [ln for ln in old.stderr.splitlines() if "deprecated" in ln] == [
        "WARNING: deprecated: synth-scene OUT_DIR is now synth-scene -o OUT_DIR (the old form "
        "goes in 0.4)"
    ]
    files = sorted(p.relative_to(tmp_path / "new") for p in (tmp_path / "new").rglob("*.png"))
    assert files and all(
        (tmp_path / "new" / f).read_bytes() == (tmp_path / "old" / f).read_bytes() for f in files
    )
    both = runner.invoke(cli, ["synth-scene", str(tmp_path / "x"), "-o", str(tmp_path / "y")])
    assert both.exit_code == 2 and "once" in both.stderr
