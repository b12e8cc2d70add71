"""Nothing outside ``-o`` is written or deleted, nothing is written through a link inside it,
and nothing stale is kept (issue 23, items 1-3).

Each test plants what a tampered or received folder could hold (a record naming ``../`` or an
absolute path, links in place of the record, of a sub-folder, of an output) and checks the
files outside the output folder byte for byte before and after; the property test does the
same with records tampered at random.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sparsetools.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
SYNTH = ROOT / "sample_data" / "synthetic"
sys.path.insert(0, str(ROOT / "tests"))


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def snapshot(folder: Path) -> dict[str, str]:
    """Every file and link below ``folder``: its bytes' hash (or the link's target)."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if p.is_symlink():
            out[rel] = "link:" + os.readlink(p)
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def make_world(tmp: Path):
    """Inputs (two synthetic scans and their calibration), a victim folder of a user's own
    files beside the output, and the output folder's path."""
    data = tmp / "data"
    for name in ("velodyne", "calib"):
        (data / name).mkdir(parents=True)
        for f in sorted((SYNTH / name).iterdir())[:2]:
            shutil.copy(f, data / name / f.name)
    victim = tmp / "victim"
    victim.mkdir()
    (victim / "000000.png").write_bytes(b"the user's own file")
    (victim / "notes.txt").write_text("keep me")
    return tmp, data, victim, tmp / "out"


@pytest.fixture
def world(tmp_path):
    return make_world(tmp_path)


def project(data: Path, out: Path, *extra):
    return run("project", data / "velodyne", "--calib", data / "calib", "--image-size",
               "1242x375", "-o", out, *extra)  # fmt: skip


def outside(tmp_path: Path, out: Path) -> dict[str, str]:
    return {k: v for k, v in snapshot(tmp_path).items() if not k.startswith(out.name + "/")}


def _tamper_outputs(out: Path, rel_of) -> None:
    journal = out / ".sparsetools" / "frames.jsonl"
    lines = []
    for line in journal.read_text().splitlines():
        d = json.loads(line)
        d["outputs"] = {role: rel_of(role, rel) for role, rel in d["outputs"].items()}
        lines.append(json.dumps(d))
    journal.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("bad", ["../victim/000000.png", "{victim}/000000.png",
                                 "calib/../../victim/notes.txt", "../../etc/hostname"])  # fmt: skip
def test_overwrite_deletes_only_recorded_files_inside_out(world, bad):
    """--overwrite removes what the record says the previous run wrote: a record naming a
    path outside -o (relative or absolute) deletes nothing there."""
    tmp, data, victim, out = world
    assert project(data, out).exit_code == 0
    _tamper_outputs(out, lambda role, rel: bad.format(victim=victim))
    (data / "velodyne" / "000001.bin").unlink()  # the next run makes only frame 000000
    before = outside(tmp, out)
    r = project(data, out, "--overwrite")
    assert r.exit_code == 0, r.output
    assert outside(tmp, out) == before


def test_a_record_folder_that_is_a_link_is_refused(world):
    tmp, data, victim, out = world
    out.mkdir()
    (out / ".sparsetools").symlink_to(victim)
    before = outside(tmp, out)
    r = project(data, out)
    assert r.exit_code == 1 and "symbolic link" in r.stderr
    assert outside(tmp, out) == before


@pytest.mark.parametrize("name", ["frames.jsonl", "run.json", "lock"])
def test_record_files_are_never_written_through_links(world, name):
    tmp, data, victim, out = world
    assert project(data, out).exit_code == 0
    target = out / ".sparsetools" / name
    target.unlink()
    target.symlink_to(victim / "notes.txt")
    (data / "velodyne" / "000001.bin").write_bytes(
        (data / "velodyne" / "000001.bin").read_bytes()[:-16]
    )  # a changed input: the run records a frame again
    before = outside(tmp, out)
    r = project(data, out)
    assert "Traceback" not in r.output
    assert outside(tmp, out) == before


@pytest.mark.parametrize("where", ["calib", "000000.png"])
def test_nothing_is_written_through_a_link_inside_out(world, where):
    """A sub-folder or an output that is a link to another folder or file is refused."""
    tmp, data, victim, out = world
    out.mkdir()
    (out / where).symlink_to(victim if where == "calib" else victim / "000000.png")
    before = outside(tmp, out)
    r = project(data, out, "--overwrite")
    assert r.exit_code == 1 and "symbolic link" in r.stderr, r.output
    assert outside(tmp, out) == before


def test_dataset_build_never_touches_a_linked_sparse_folder(tmp_path):
    """A plain append into a dataset whose sparse/ is a link: refused, the linked folder's
    files untouched."""
    rgb, sparse = tmp_path / "rgb", tmp_path / "sparse_maps"
    assert run("project", SYNTH / "velodyne", "--calib", SYNTH / "calib", "--image-size",
               "1242x375", "-o", sparse).exit_code == 0  # fmt: skip
    shutil.copytree(SYNTH / "image_2", rgb)
    ds = tmp_path / "ds"
    args = ["dataset", "build", "-o", ds, "--rgb", rgb, "--sparse", sparse, "--calib",
            SYNTH / "calib", "--sparse-format", "parquet"]  # fmt: skip
    assert run(*args).exit_code == 0
    elsewhere = tmp_path / "elsewhere"
    shutil.move(ds / "sparse", elsewhere)
    (elsewhere / "part-99999.parquet").write_bytes(b"someone else's")
    (ds / "sparse").symlink_to(elsewhere)
    before = snapshot(elsewhere)
    (rgb / "000003.png").write_bytes((rgb / "000000.png").read_bytes())
    shutil.copy(sparse / "000000.png", sparse / "000003.png")
    r = run(*args, "--overwrite")
    assert r.exit_code == 1 and "symbolic link" in r.stderr, r.output
    assert snapshot(elsewhere) == before


@pytest.mark.parametrize("split", ["../../x", "{tmp}/x", "a/b", ".."])
def test_export_split_is_one_folder_inside_out(tmp_path, split):
    maps = tmp_path / "maps" / "2011_09_26_drive_0001_sync"
    maps.mkdir(parents=True)
    shutil.copy(SYNTH / "depth_gt" / "000000.png", maps / "0000000000.png")
    before = snapshot(tmp_path)
    out = tmp_path / "a" / "b" / "out"
    r = run("dataset", "export", tmp_path / "maps", "--split", split.format(tmp=tmp_path),
            "-o", out)  # fmt: skip
    assert r.exit_code != 0 and "--split" in r.stderr and "Traceback" not in r.output
    assert snapshot(tmp_path) == before


# -- nothing stale kept -----------------------------------------------------------------------------


def test_a_truncated_output_is_recomputed(world):
    _, data, _, out = world
    assert project(data, out).exit_code == 0
    png = out / "000001.png"
    good = png.read_bytes()
    png.write_bytes(good[: len(good) // 2])
    r = project(data, out, "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["processed"] == 1
    assert png.read_bytes() == good


def test_an_edited_output_of_the_same_size_is_recomputed(world):
    _, data, _, out = world
    assert project(data, out).exit_code == 0
    png = out / "000000.png"
    good = png.read_bytes()
    png.write_bytes(good[:-1] + bytes([good[-1] ^ 0xFF]))  # same size, new mtime
    r = project(data, out, "--json")
    assert json.loads(r.stdout)["processed"] == 1 and png.read_bytes() == good


def test_an_input_changed_while_its_frame_ran_is_not_recorded(tmp_path):
    """Identities are taken before a frame runs and checked after: a frame whose input
    changed meanwhile keeps no record and is recomputed by the next run."""
    from _pipeline_jobs import ChangeInput, RandomInput
    from sparsetools.io.provenance import read_frame_records
    from sparsetools.io.sources import FrameKey
    from sparsetools.pipeline import FrameTask, RunSpec, run_frames

    src = tmp_path / "a.dat"
    src.write_bytes(b"x" * 100)
    out = tmp_path / "out"
    task = FrameTask(FrameKey("", "a"), RandomInput(str(src)), {"data": out / "a.bin"}, (src,))
    spec = RunSpec("test", out, {"seed": 1})
    s = run_frames(ChangeInput(), [task], spec=spec)
    assert s.inputs_changed == ["a"] and "a" not in read_frame_records(out)
    again = run_frames(ChangeInput(change=False), [task], spec=spec)
    assert len(again.done) == 1 and "a" in read_frame_records(out)
    assert len(run_frames(ChangeInput(change=False), [task], spec=spec).resumed) == 1


def test_a_run_refused_by_the_lock_leaves_the_running_run_alone(world):
    """The lock is taken before any clean-up: a second run into a folder being written does not
    delete the first run's temporary files."""
    from sparsetools.io.atomic import TMP_PREFIX
    from sparsetools.io.provenance import hold_lock

    _, data, _, out = world
    assert project(data, out).exit_code == 0
    tmp_file = out / f"{TMP_PREFIX}12345-0-abcdef.png"
    tmp_file.write_bytes(b"being written by the first run")
    with hold_lock(out):
        r = project(data, out, "--overwrite")
    assert r.exit_code == 1 and "another sparsetools run" in r.stderr
    assert tmp_file.read_bytes() == b"being written by the first run"
    assert project(data, out).exit_code == 0 and not tmp_file.exists()  # ours: cleaned after


def test_a_folder_of_020_gets_output_identities_on_its_next_run(world):
    _, data, _, out = world
    assert project(data, out).exit_code == 0
    journal = out / ".sparsetools" / "frames.jsonl"
    old = [json.loads(line) for line in journal.read_text().splitlines()]
    journal.write_text("".join(json.dumps({k: v for k, v in d.items() if k != "output_ids"})
                               + "\n" for d in old))  # fmt: skip
    r = project(data, out, "--json")
    assert json.loads(r.stdout)["skipped_existing"] == 2
    assert all("output_ids" in json.loads(line) for line in journal.read_text().splitlines())


# -- discovery -------------------------------------------------------------------------------------


@pytest.mark.timeout(120)  # without the guard the walk explodes: a hang is a failure
def test_discovery_follows_a_link_once(tmp_path):
    """``ln -s . x`` inside an input folder does not repeat its frames, and two such links do
    not make the walk explode."""
    data = tmp_path / "velodyne"
    data.mkdir()
    for f in sorted((SYNTH / "velodyne").iterdir()):
        shutil.copy(f, data / f.name)
    (data / "x").symlink_to(".")
    (data / "y").symlink_to(".")
    (data / "sub").mkdir()
    (data / "sub" / "up").symlink_to("..")
    r = run("project", data, "--calib", SYNTH / "calib" / "000000.txt", "--image-size",
            "1242x375", "-o", tmp_path / "out", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["frames"] == 3


# -- records tampered at random --------------------------------------------------------------------

_PATHS = st.sampled_from(["../victim/000000.png", "{victim}/notes.txt", "/", "",
                          "a/../../victim/notes.txt", "calib/../../../victim", "000000.png",
                          "linked/000000.png", "..", ".", "\x00"])  # fmt: skip
_JUNK = st.one_of(st.none(), st.integers(), st.floats(allow_nan=True), st.lists(st.integers()),
                  st.text(max_size=5), _PATHS)  # fmt: skip


@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture,
                                 HealthCheck.too_slow])  # fmt: skip
@given(
    outputs=st.lists(_PATHS, min_size=1, max_size=3),
    field=st.sampled_from(["outputs", "inputs", "stats", "key", "output_ids", None]),
    junk=_JUNK,
    run_field=st.sampled_from(["command", "version", "settings", None]),
    overwrite=st.booleans(),
    link=st.booleans(),
)
def test_tampered_records_never_reach_outside_out(
    tmp_path_factory, outputs, field, junk, run_field, overwrite, link
):
    """Whatever a record holds (paths out of the folder, links, wrong types), a rerun with or
    without --overwrite creates, changes and deletes nothing outside -o."""
    tmp, data, victim, out = make_world(tmp_path_factory.mktemp("tamper"))
    assert project(data, out).exit_code == 0
    if link:
        (out / "linked").symlink_to(victim)
    rec = out / ".sparsetools"
    lines = []
    for i, line in enumerate((rec / "frames.jsonl").read_text().splitlines()):
        d = json.loads(line)
        d["outputs"] = {role: outputs[i % len(outputs)].format(victim=victim)
                        for role in d["outputs"]}  # fmt: skip
        if field is not None:
            d[field] = junk
        lines.append(json.dumps(d))
    (rec / "frames.jsonl").write_text("\n".join(lines) + "\n")
    if run_field is not None:
        doc = json.loads((rec / "run.json").read_text())
        doc[run_field] = junk
        (rec / "run.json").write_text(json.dumps(doc))
    (data / "velodyne" / "000001.bin").unlink()
    before = outside(tmp, out)
    r = project(data, out, *(["--overwrite"] if overwrite else []))
    assert "Traceback" not in r.output
    assert outside(tmp, out) == before


def test_pipeline_never_replaces_a_users_report(tmp_path):
    """``pipeline`` writes OUT/report.md and OUT/steps.json: a user's own files of those names
    are refused before any step runs (--overwrite replaces them); its own are rewritten."""
    config = tmp_path / "c.yaml"
    config.write_text("name: t\nsteps:\n  - name: scene\n    run: synth-scene -o ${out}/s "
                      "--frames 1 --image-size 32x16 --underwater-frames 0\n")  # fmt: skip
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.md").write_text("my own notes")
    r = run("pipeline", config, "-o", out)
    assert r.exit_code == 1 and "report.md" in r.stderr
    assert (out / "report.md").read_text() == "my own notes" and not (out / "s").exists()
    assert run("pipeline", config, "-o", out, "--overwrite").exit_code == 0
    assert "my own notes" not in (out / "report.md").read_text()
    assert run("pipeline", config, "-o", out).exit_code == 0  # its own report: rewritten


# -- a calibration of another sensor ----------------------------------------------------------------


def test_a_kitti_scan_with_a_nuscenes_calibration_is_refused(tmp_path, nuscenes_demo):
    """A KITTI Velodyne scan projected with a nuScenes LIDAR_TOP calibration gave 1600x900 maps
    in silence; the other way round too: both are refused, naming the sensor."""
    kitti = ROOT / "sample_data" / "kitti"
    r = run("project", kitti / "velodyne" / "000001.bin", "--calib",
            nuscenes_demo / "calib_derived_from_pkl.json", "-o", tmp_path / "a")  # fmt: skip
    assert r.exit_code == 1 and "nuScenes LIDAR_TOP" in r.stderr and "KITTI Velodyne" in r.stderr
    assert not list((tmp_path / "a").rglob("*.png"))
    sweep = next(nuscenes_demo.glob("*LIDAR_TOP*.pcd.bin"))
    r = run("project", sweep, "--calib", kitti / "calib" / "000001.txt", "--image-size",
            "1242x375", "-o", tmp_path / "b")  # fmt: skip
    assert r.exit_code == 1 and "is for the KITTI Velodyne" in r.stderr, r.output
    ok = run("project", sweep, "--calib", nuscenes_demo / "calib_derived_from_pkl.json",
             "-o", tmp_path / "c")  # fmt: skip
    assert ok.exit_code == 0, ok.output
