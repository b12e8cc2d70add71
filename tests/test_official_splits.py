"""The official split lists shipped with the package (``--split NAME``): their counts, the
catalogue, matching a KITTI raw tree whose drive is an Eigen test drive and a nuScenes tree,
the report of lines that matched nothing, and the option's usage errors and 0.2 spelling."""

from __future__ import annotations

import fnmatch
import json
import lzma
import re
import shutil
from collections import Counter
from importlib import resources
from pathlib import Path

import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.pipeline.dataset.official_splits import (
    ODOMETRY_DRIVES,
    OFFICIAL_SPLITS,
    official_split,
    official_split_lists,
    official_split_names,
    shipped_split_lines,
)
from sparsetools.pipeline.dataset.splits import SplitList, split_file_assignments

ROOT = Path(__file__).resolve().parent.parent
SHIPPED = resources.files("sparsetools") / "data" / "splits"
SHARED_SPLITS = ROOT.parent / "shared" / "data" / "splits"

#: The line counts of data/splits/README.txt (and ../shared/data/splits/README.txt).
README_COUNTS = {
    ("kitti", "eigen_test_files.txt"): 697,
    ("kitti", "eigen_benchmark_test_files.txt"): 652,
    ("kitti", "eigen_zhou_train_files.txt"): 39810,
    ("kitti", "eigen_zhou_val_files.txt"): 4424,
    ("kitti", "eigen_full_train_files.txt"): 45200,
    ("kitti", "eigen_full_val_files.txt"): 1776,
    ("nuscenes", "train_scenes.txt"): 700,
    ("nuscenes", "val_scenes.txt"): 150,
    ("nuscenes", "test_scenes.txt"): 150,
    ("nuscenes", "mini_train_scenes.txt"): 8,
    ("nuscenes", "mini_val_scenes.txt"): 2,
}

DATE = "2011_09_26"
#: An Eigen test drive (its frames 0, 3, 6 ... 75 are in eigen_test_files.txt).
DRIVE = f"{DATE}_drive_0002_sync"
N_FRAMES = 7  # frames 0-6 of the real sequence: 0, 3 and 6 are Eigen test frames


def run(*args):
    return CliRunner().invoke(cli, [*map(str, args)])


def summary(*args) -> dict:
    r = run("-q", *args, "--json")
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


# -- the shipped lists ------------------------------------------------------------------------------
def _unpacked(dataset: str, file: str) -> bytes:
    """A shipped list's bytes (stored as ``<file>.xz``)."""
    return lzma.decompress((SHIPPED / dataset / f"{file}.xz").read_bytes())


@pytest.mark.parametrize(("dataset", "file"), sorted(README_COUNTS))
def test_each_shipped_list_loads_with_the_readmes_count(dataset, file):
    lines = shipped_split_lines(dataset, file)
    assert len(lines) == README_COUNTS[(dataset, file)]
    raw = _unpacked(dataset, file).decode("utf-8").splitlines()
    assert len(lines) == sum(1 for line in raw if line.strip())  # every line read, none dropped
    if dataset == "kitti":  # <date>/<drive>_sync <frame> <l|r>
        pattern = re.compile(r"^(\d{4}_\d\d_\d\d)/\1_drive_\d{4}_sync$")
        assert all(pattern.match(p[0]) and p[1].isdigit() and p[2] in "lr" for p in lines)
    else:
        assert all(len(p) == 1 and re.fullmatch(r"scene-\d{4}", p[0]) for p in lines)
        assert len(set(lines)) == len(lines)


def test_the_readme_states_the_counts_the_lists_have():
    """The shipped README (the attribution) gives the same counts as the files."""
    text = (SHIPPED / "README.txt").read_text(encoding="utf-8")
    for (dataset, file), n in README_COUNTS.items():
        if dataset == "kitti":
            m = re.search(rf"{re.escape(file)}\s+(\d+)", text)
        else:
            m = re.search(rf"{re.escape(file)} (\d+)", text)
        assert m and int(m.group(1)) == n == len(shipped_split_lines(dataset, file)), file
    for source in ("nianticlabs/monodepth2", "b676244", "CC BY-NC-SA 3.0", "nuscenes-devkit",
                   "d9de17a", "Apache-2.0", "odometry development kit"):  # fmt: skip
        assert source in text


def test_the_shipped_lists_are_verbatim_copies(real_dir):
    """Byte for byte the lists of ../shared/data/splits (when present, as real data is)."""
    for dataset in ("kitti", "nuscenes"):
        files = sorted(p.name for p in (SHARED_SPLITS / dataset).glob("*.txt"))
        assert files == sorted(
            p.name[: -len(".xz")] for p in (SHIPPED / dataset).iterdir() if p.name.endswith(".xz")
        )
        for name in files:
            assert _unpacked(dataset, name) == (SHARED_SPLITS / dataset / name).read_bytes()


def test_the_lists_are_package_data():
    """pyproject's package-data globs take every shipped list and the README into the wheel."""
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")  # no tomllib on Python 3.10
    section = text.split("[tool.setuptools.package-data]", 1)[1].split("\n[", 1)[0]
    globs = re.findall(r'"([^"]+)"', re.search(r"^sparsetools = \[(.*)\]$", section, re.M)[1])
    assert "data/*.json" in globs
    pkg = ROOT / "src" / "sparsetools"
    files = [p.relative_to(pkg).as_posix() for p in (pkg / "data" / "splits").rglob("*")
             if p.is_file()]  # fmt: skip
    assert "data/splits/README.txt" in files and len(files) == 1 + 9 + 7
    assert all(f.endswith(".txt.xz") for f in files if f != "data/splits/README.txt")
    assert all(any(fnmatch.fnmatch(f, g) for g in globs) for f in files)


def test_a_compressed_split_file_reads_as_its_text(tmp_path):
    """``--split-file`` takes an xz-compressed list as the shipped ones are stored; a broken
    or oversized one is refused in one line."""
    from sparsetools.pipeline.dataset import splits

    text = "2011_09_26/2011_09_26_drive_0002_sync 0000000003 l\n# a comment\nseqA/000001\n"
    (tmp_path / "a.txt").write_text(text)
    (tmp_path / "a.txt.xz").write_bytes(lzma.compress(text.encode()))
    assert splits.read_split_file(tmp_path / "a.txt.xz") == splits.read_split_file(
        tmp_path / "a.txt"
    )
    (tmp_path / "cut.txt.xz").write_bytes(lzma.compress(text.encode())[:-9])
    (tmp_path / "big.txt.xz").write_bytes(lzma.compress(b"x\n" * 1000))
    for name, why in (("cut.txt.xz", "cannot read split file"), ("big.txt.xz", "MiB of text")):
        with pytest.raises(ParameterError, match=why):
            if name == "big.txt.xz":
                with pytest.MonkeyPatch.context() as mp:
                    mp.setattr(splits, "MAX_SPLIT_TEXT", 1000)
                    splits.read_split_file(tmp_path / name)
            else:
                splits.read_split_file(tmp_path / name)


def test_each_name_maps_to_its_lists():
    def files(name):
        return {s.name: Path(s.source).name for s in official_split_lists(name)}

    zhou = {"train": "eigen_zhou_train_files.txt", "val": "eigen_zhou_val_files.txt"}
    assert files("eigen") == {**zhou, "test": "eigen_test_files.txt"}
    assert files("eigen_benchmark") == {**zhou, "test": "eigen_benchmark_test_files.txt"}
    assert files("eigen_full") == {"train": "eigen_full_train_files.txt",
                                   "val": "eigen_full_val_files.txt",
                                   "test": "eigen_test_files.txt"}  # fmt: skip
    assert files("odom") == {"train": "odom_train_files.txt", "val": "odom_val_files.txt"}
    assert files("official") == {"train": "train_scenes.txt", "val": "val_scenes.txt",
                                 "test": "test_scenes.txt"}  # fmt: skip
    assert files("mini") == {"train": "mini_train_scenes.txt", "val": "mini_val_scenes.txt"}
    assert official_split_names("kitti") == ("eigen", "eigen_full", "eigen_benchmark", "odom")
    assert official_split_names("nuscenes") == ("official", "mini")
    assert set(official_split_names()) == set(OFFICIAL_SPLITS)
    with pytest.raises(ParameterError, match="the official splits are official, mini"):
        official_split("eigen", "nuscenes")
    with pytest.raises(ParameterError, match="unknown split 'zhou'"):
        official_split("zhou")


def test_the_help_names_the_catalogues_splits():
    from sparsetools.cli.dataset_options import SPLIT_NAMES

    for dataset, names in SPLIT_NAMES.items():
        assert names == official_split_names(dataset)
        for command in (["kitti-raw"], ["build"]) if dataset == "kitti" else (["nuscenes"],):
            text = " ".join(run("dataset", *command, "--help").output.split())
            assert all(n in text for n in names), (command, text)


def test_the_splits_of_a_name_never_share_a_frame_of_one_camera():
    """Eigen-Zhou train and val share 3,950 frames, each with the other side: per camera no
    frame is in two splits, so a dataset of image_02 (or image_03) is well defined."""
    for name in official_split_names("kitti"):
        seen: dict[tuple, str] = {}
        for s in official_split_lists(name):
            for p in s.lines:
                key = (p[0].rpartition("/")[2], int(p[1]), p[2])
                assert seen.setdefault(key, s.name) == s.name, (name, key)
    zhou = official_split_lists("eigen")
    train = {(p[0], int(p[1])) for p in zhou[0].lines}
    val = {(p[0], int(p[1])) for p in zhou[1].lines}
    assert len(train & val) == 3950


def test_odometry_lines_are_read_as_raw_drives():
    """``8 4056 r`` is frame 1100 + 4056 of 2011_09_30_drive_0028 (the devkit's table); every
    odometry line lands inside its sequence's raw frame range."""
    raw = shipped_split_lines("kitti", "odom_train_files.txt")
    train = official_split_lists("odom")[0].lines
    assert raw[0] == ("8", "4056", "r")
    assert train[0] == ("2011_09_30/2011_09_30_drive_0028_sync", "5156", "r")
    end = {0: 4540, 1: 1100, 2: 4660, 3: 800, 4: 270, 5: 2760, 6: 1100, 7: 1100, 8: 5170}
    for s in official_split_lists("odom"):
        for line in s.lines:
            seq = next(k for k, (d, _) in ODOMETRY_DRIVES.items() if d == line[0])
            assert ODOMETRY_DRIVES[seq][1] <= int(line[1]) <= end[seq]


# -- matching and the report --------------------------------------------------------------------


def test_a_line_of_the_other_camera_is_no_match():
    samples = {"d1/0000000005": "d1", "d1/0000000006": "d1", "d2/image_03/0000000005": "d2"}
    lists = [SplitList("test", "t.txt", (("x/d1", "5", "l"), ("x/d1", "6", "r"),
                                         ("x/d2", "5", "r"), ("x/d9", "5", "l")))]  # fmt: skip
    assignment, report = split_file_assignments(lists, samples, camera=2)
    # d1 is image_02 (the camera built); d2's id names image_03, which its r line matches
    assert assignment == {"d1/0000000005": "test", "d2/image_03/0000000005": "test"}
    (r,) = report.lists
    assert (r.listed, r.present, r.absent, r.other_camera) == (4, 2, 1, 1)
    assert r.absent_groups == {"d9": (1, 1)} and report.missing == 2
    # camera unknown: the side is not checked for ids that do not name one
    assignment, report = split_file_assignments(lists, samples)
    assert set(assignment) == set(samples) and report.lists[0].other_camera == 0


def test_a_scene_line_takes_every_sample_of_its_scene():
    samples = {"scene-0061/a": "scene-0061", "scene-0061/b": "scene-0061", "scene-0103/c":
               "scene-0103"}  # fmt: skip
    lists = [SplitList("train", "tr.txt", (("scene-0061",), ("scene-0553",))),
             SplitList("val", "va.txt", (("scene-0916",),))]  # fmt: skip
    assignment, report = split_file_assignments(lists, samples, name="mini")
    assert assignment == {"scene-0061/a": "train", "scene-0061/b": "train"}
    train, val = report.lists
    assert (train.present, train.absent, val.present, val.absent) == (1, 1, 0, 1)
    lines = report.lines()
    assert lines[0] == "mini train: 2 listed, 1 present, 1 absent: scenes scene-0553"
    assert lines[1] == "mini val: 1 listed, 0 present, 1 absent: scenes scene-0916"


def test_the_report_names_a_few_drives_and_counts_the_rest():
    """Independent count from the shipped file: drives of eigen test with their lines."""
    test = official_split_lists("eigen")[2]
    per_drive = Counter(p[0].rpartition("/")[2] for p in test.lines)
    samples = {f"{DRIVE}/{i:010d}": DRIVE for i in (0, 3, 6, 1)}
    _, report = split_file_assignments([test], samples, camera=2, name="eigen")
    (r,) = report.lists
    assert (r.listed, r.present, r.absent) == (697, 3, 694)
    assert r.absent_groups == {d: (n - 3 if d == DRIVE else n, n)
                               for d, n in sorted(per_drive.items())}  # fmt: skip
    first = sorted(per_drive)[:3]
    assert first[0] == DRIVE
    assert report.lines()[0] == (
        f"eigen test: 697 listed, 3 present, 694 absent: drives {DRIVE} (22 of 25), "
        f"{first[1]} ({per_drive[first[1]]}), {first[2]} ({per_drive[first[2]]}) and "
        f"{len(per_drive) - 3} more"
    )


# -- a KITTI raw tree whose drive is an Eigen test drive --------------------------------------------


@pytest.fixture(scope="module")
def eigen_tree(real_dir, tmp_path_factory):
    """raw/2011_09_26/2011_09_26_drive_0002_sync: frames 0-6 of the real sequence under the
    name of an Eigen test drive (frames 0, 3, 6 listed in its test split; 1, 2, 4, 5 not)."""
    seq = real_dir / "kitti-raw-sequence-2011_09_26"
    root = tmp_path_factory.mktemp("eigen_raw")
    date = root / DATE
    date.mkdir()
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(seq / name, date / name)
    for i in range(N_FRAMES):
        for sub, ext in (("velodyne_points", ".bin"), ("image_02", ".png")):
            folder = date / DRIVE / sub / "data"
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copy(seq / sub / "data" / f"{i:010d}{ext}", folder / f"{i:010d}{ext}")
    return root


@pytest.fixture(scope="module")
def eigen_dataset(eigen_tree, tmp_path_factory):
    out = tmp_path_factory.mktemp("eigen_ds") / "ds"
    return out, summary("dataset", "kitti-raw", eigen_tree, "-o", out, "--split", "eigen")


def _listed(file: str) -> set[int]:
    return {int(p[1]) for p in shipped_split_lines("kitti", file) if p[0].endswith(DRIVE)}


def test_the_tree_splits_as_the_eigen_lists_say(eigen_dataset):
    from sparsetools.io.dataset_reader import DatasetReader

    out, s = eigen_dataset
    in_test = sorted(_listed("eigen_test_files.txt") & set(range(N_FRAMES)))
    assert in_test == [0, 3, 6]
    rows = DatasetReader(out).manifest.to_pylist()
    assert {r["id"]: r["split"] for r in rows} == {f"{DRIVE}/{i:010d}": "test" for i in in_test}
    assert s["splits"] == {"test": 3} and s["unmatched"]["not_in_split_files"] == N_FRAMES - 3
    lists = {x["split"]: x for x in s["split_lists"]["lists"]}
    assert s["split_lists"]["name"] == "eigen" and s["split_lists"]["not_listed"] == 4
    assert (lists["test"]["listed"], lists["test"]["present"], lists["test"]["absent"]) == (
        697, 3, 694)  # fmt: skip
    assert lists["test"]["absent_drives"][DRIVE] == {"absent": 22, "listed": 25}
    assert lists["train"]["present"] == 0 and lists["train"]["absent"] == 39810
    assert lists["val"]["absent"] == 4424 and len(s["split_report"]) == 4
    assert s["split_report"][2].startswith(
        f"eigen test: 697 listed, 3 present, 694 absent: drives {DRIVE} (22 of 25), "
    )
    assert (
        s["split_report"][3] == "4 frame(s) of the inputs are in none of the eigen lists: left out"
    )


def test_the_manifest_records_the_official_split(eigen_dataset):
    from sparsetools.io.dataset_reader import DatasetReader

    out, _ = eigen_dataset
    split = DatasetReader(out).info["split"]
    assert split["method"] == "official" and split["name"] == "eigen"
    assert split["files"]["test"] == "kitti/eigen_test_files.txt"
    assert split["listed"] == 697 + 39810 + 4424 and split["missing"] == split["listed"] - 3
    info = json.loads(run("dataset", "info", out, "--json").stdout)
    assert info["official_split"] == "eigen" and info["split_method"]["name"] == "eigen"
    text = run("dataset", "info", out).stdout
    assert re.search(r"split by\s+official split eigen \(", text)


def test_a_rerun_is_a_no_op_and_another_name_is_refused(eigen_tree, eigen_dataset):
    out, _ = eigen_dataset
    again = summary("dataset", "kitti-raw", eigen_tree, "-o", out, "--split", "eigen")
    assert again["processed"] == 0 and again["skipped_existing"] == 3
    r = run("-q", "dataset", "kitti-raw", eigen_tree, "-o", out, "--split", "eigen_benchmark")
    assert r.exit_code == 1
    assert "made with --split eigen, not eigen_benchmark" in r.stderr


def test_the_text_summary_shows_each_list_on_its_line(eigen_tree, eigen_dataset):
    out, _ = eigen_dataset
    r = run("-q", "dataset", "kitti-raw", eigen_tree, "-o", out, "--split", "eigen")
    lines = r.stdout.splitlines()
    i = next(n for n, line in enumerate(lines) if line.startswith("split report"))
    assert "eigen train: 39810 listed, 0 present, 39810 absent: drives " in lines[i]
    assert lines[i + 2].strip().startswith("eigen test: 697 listed, 3 present, 694 absent")
    assert (
        lines[i + 3].strip() == "4 frame(s) of the inputs are in none of the eigen lists: left out"
    )
    assert not any("absent_drives" in line for line in lines)  # the detail is --json's


def test_eigen_benchmark_takes_its_own_test_frames(eigen_tree, tmp_path):
    s = summary("dataset", "kitti-raw", eigen_tree, "-o", tmp_path / "ds", "--split",
                "eigen_benchmark")  # fmt: skip
    expected = sorted(_listed("eigen_benchmark_test_files.txt") & set(range(N_FRAMES)))
    assert expected == [6] and s["splits"] == {"test": 1}
    test = next(x for x in s["split_lists"]["lists"] if x["split"] == "test")
    assert (test["listed"], test["present"]) == (652, 1)


def test_dataset_build_takes_the_same_names(eigen_tree, eigen_dataset, tmp_path):
    out, _ = eigen_dataset
    s = summary("dataset", "build", "-o", tmp_path / "ds", "--rgb", eigen_tree, "--sparse",
                out / ".sources" / "gt", "--split", "eigen")  # fmt: skip
    assert s["splits"] == {"test": 3} and s["split_lists"]["name"] == "eigen"


def test_right_camera_lines_are_counted_not_matched(eigen_tree, tmp_path):
    """The dataset is image_02: an ``r`` line of a present frame is of the other camera."""
    listed = tmp_path / "test_files.txt"
    listed.write_text(f"{DATE}/{DRIVE} 0 r\n{DATE}/{DRIVE} 3 r\n{DATE}/{DRIVE} 6 l\n"
                      f"{DATE}/{DATE}_drive_0009_sync 6 l\n")  # fmt: skip
    s = summary("dataset", "kitti-raw", eigen_tree, "-o", tmp_path / "ds", "--split-file",
                f"test={listed}")  # fmt: skip
    assert s["splits"] == {"test": 1}
    (test,) = s["split_lists"]["lists"]
    assert (test["present"], test["other_camera"], test["absent"]) == (1, 2, 1)
    assert s["split_report"][0] == (
        f"test (test_files.txt): 4 listed, 1 present, 1 absent, 2 of the other camera: drives "
        f"{DATE}_drive_0009_sync"
    )


# -- nuScenes ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def nuscenes_root(real_dir, tmp_path_factory):
    from _nuscenes_tree import build_tree

    root = tmp_path_factory.mktemp("nuscenes")
    build_tree(real_dir, root)
    return root


def _nuscenes(root, out, *extra):
    return summary("dataset", "nuscenes", root, "-o", out, "--sweeps", "1", *extra)


def test_nuscenes_official_split(nuscenes_root, tmp_path):
    """The tree's one sample is of scene-0061, a train scene of the official split."""
    s = _nuscenes(nuscenes_root, tmp_path / "ds", "--split", "official")
    assert s["splits"] == {"train": 1} and s["unmatched"]["not_in_split_files"] == 0
    counts = {x["split"]: (x["listed"], x["present"], x["absent"])
              for x in s["split_lists"]["lists"]}  # fmt: skip
    assert counts == {"train": (700, 1, 699), "val": (150, 0, 150), "test": (150, 0, 150)}
    assert "scene-0061" not in s["split_lists"]["lists"][0]["absent_scenes"]
    assert len(s["split_lists"]["lists"][0]["absent_scenes"]) == 699
    assert s["split_report"][-1] == "every frame of the inputs is in one of the official lists"
    info = json.loads(run("dataset", "info", tmp_path / "ds", "--json").stdout)
    assert info["official_split"] == "official"
    mini = _nuscenes(nuscenes_root, tmp_path / "mini", "--split", "mini")
    assert mini["splits"] == {"train": 1}
    assert mini["split_report"][1] == (
        "mini val: 2 listed, 0 present, 2 absent: scenes scene-0103, scene-0916"
    )


def test_nuscenes_split_file(nuscenes_root, tmp_path):
    (tmp_path / "held.txt").write_text("# my scenes\nscene-0061\nscene-0103\n")
    s = _nuscenes(
        nuscenes_root, tmp_path / "ds", "--split-file", f"holdout={tmp_path / 'held.txt'}"
    )
    assert s["splits"] == {"holdout": 1}
    assert (
        s["split_report"][0]
        == "holdout (held.txt): 2 listed, 1 present, 1 absent: scenes scene-0103"
    )
    (tmp_path / "other.txt").write_text("scene-0103\n")
    r = run("-q", "dataset", "nuscenes", nuscenes_root, "-o", tmp_path / "none", "--sweeps", "1",
            "--split-file", f"val={tmp_path / 'other.txt'}")  # fmt: skip
    assert r.exit_code == 1 and "no frame is listed in the split file(s)" in r.stderr
    (tmp_path / "bad.txt").write_text("scene-0061 5 l\n")
    r = run("-q", "dataset", "nuscenes", nuscenes_root, "-o", tmp_path / "bad", "--sweeps", "1",
            "--split-file", f"val={tmp_path / 'bad.txt'}")  # fmt: skip
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 1 and len(lines) == 1 and "one scene name per line" in lines[0]
    assert not (tmp_path / "bad").exists()


# -- the option ---------------------------------------------------------------------------------------


@pytest.fixture
def routes(monkeypatch):
    """The routes replaced by a recorder of what the command passes them."""
    from sparsetools.pipeline import RunSummary
    from sparsetools.pipeline.dataset import roots

    calls = []

    def fake(root, out_dir, **kw):
        calls.append({k: kw.get(k) for k in ("split", "split_files", "official_split")})
        return RunSummary(command="dataset build", output=out_dir)

    monkeypatch.setattr(roots, "build_kitti_raw_dataset", fake)
    monkeypatch.setattr(roots, "build_nuscenes_dataset", fake)
    return calls


@pytest.mark.parametrize(("command", "name"), [("kitti-raw", "eigen"), ("nuscenes", "official")])
def test_a_name_reaches_the_route(routes, tmp_path, command, name):
    r = run("dataset", command, tmp_path, "-o", tmp_path / "ds", "--split", name)
    assert r.exit_code == 0, r.output
    assert routes == [{"split": None, "split_files": None, "official_split": name}]


@pytest.mark.parametrize("command", ["kitti-raw", "nuscenes"])
def test_split_splits_and_split_file_are_one_choice(routes, tmp_path, command):
    lst = tmp_path / "train.txt"
    lst.write_text("scene-0061\n")
    name = "eigen" if command == "kitti-raw" else "official"
    base = ["dataset", command, tmp_path, "-o", tmp_path / "ds"]
    for extra in (["--split", name, "--splits", "0.5,0.5"], ["--split", name, "--split-file", lst],
                  ["--splits", "0.5,0.5", "--split-file", lst]):  # fmt: skip
        r = run(*base, *extra)
        err = [line for line in r.stderr.splitlines() if line.startswith("Error")]
        assert r.exit_code == 2 and len(err) == 1, r.output
        assert "give one of --split, --splits and --split-file" in err[0]
    assert routes == [] and not (tmp_path / "ds").exists()


@pytest.mark.parametrize(
    ("command", "names"),
    [("kitti-raw", "eigen, eigen_full, eigen_benchmark, odom"), ("build", None),
     ("nuscenes", "official, mini")],
)  # fmt: skip
def test_an_unknown_name_lists_the_known_ones(routes, tmp_path, command, names):
    args = ["dataset", command, tmp_path, "-o", tmp_path / "ds"]
    if command == "build":
        args = ["dataset", "build", "-o", tmp_path / "ds", "--rgb", tmp_path, "--sparse", tmp_path]
        names = "eigen, eigen_full, eigen_benchmark, odom"
    for bad in ("zhou", "mini" if command != "nuscenes" else "eigen"):
        r = run(*args, "--split", bad)
        err = [line for line in r.stderr.splitlines() if line.startswith("Error")]
        assert r.exit_code == 2 and len(err) == 1, r.output
        assert f"unknown split '{bad}': the official splits are {names}" in err[0]


def test_the_fraction_spelling_still_works_and_warns_once(routes, tmp_path):
    base = ["dataset", "kitti-raw", tmp_path, "-o", tmp_path / "ds"]
    r = run(*base, "--split", "0.6,0.2,0.2")
    assert r.exit_code == 0, r.output
    assert routes == [{"split": {"train": 0.6, "val": 0.2, "test": 0.2}, "split_files": None,
                       "official_split": None}]  # fmt: skip
    warned = [line for line in r.stderr.splitlines() if "deprecated" in line]
    assert warned == ["WARNING: deprecated: --split 0.6,0.2,0.2 is now --splits 0.6,0.2,0.2 "
                      "(--split NAME picks an official split; its fraction spelling goes in 0.4)"]  # fmt: skip
    bad = run(*base, "--split", "0.6,x")  # read as --splits reads it, named as typed
    assert bad.exit_code == 2 and "Invalid value for '--split'" in bad.stderr
    assert "split fractions as numbers" in bad.stderr and len(routes) == 1


# -- a shipped list by name where a split file is taken (--split-file eigen:test) -----------------


def test_shipped_list_by_name_is_the_shipped_file():
    from sparsetools.pipeline.dataset.official_splits import shipped_split_file

    part, path = shipped_split_file("eigen:test")
    assert part == "test" and path.name == "eigen_test_files.txt.xz"
    lines = [ln for ln in lzma.decompress(path.read_bytes()).decode().splitlines() if ln.strip()]
    assert len(lines) == 697
    part, path = shipped_split_file("official:val")
    assert len(lzma.decompress(path.read_bytes()).split()) == 150
    for bad in ("eigen", "eigen:nope", "nope:test", "mini:test"):
        with pytest.raises(ParameterError):
            shipped_split_file(bad)


@pytest.mark.real
def test_split_file_option_takes_a_shipped_list(real_dir, tmp_path):
    # The export reads the shipped Eigen test list: every line names a drive the real
    # sequence is not, so the refusal names the shipped file (the list was found and read).
    tree = real_dir / "kitti-raw-sequence-2011_09_26"
    r = run("dataset", "export", tree, "-o", tmp_path / "gt", "--layout", "monodepth2-gt",
            "--split-file", "eigen:test")  # fmt: skip
    assert r.exit_code != 0 and "697 of the 697 lines" in r.output
    assert "eigen_test_files.txt" in r.output and "Traceback" not in r.output
    bad = run("dataset", "export", tree, "-o", tmp_path / "gt", "--layout", "monodepth2-gt",
              "--split-file", "eigen:nope")  # fmt: skip
    assert bad.exit_code == 2 and "has no 'nope' list" in bad.output
    assert not (tmp_path / "gt").exists()
