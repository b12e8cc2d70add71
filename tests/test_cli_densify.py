"""``sparsetools densify``: every method against the library, layouts, radar, formats,
summary, workers, bad input."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.ops.densify import DensifySettings, densify

SYNTH = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"
FRAMES = ("000000", "000001", "000002")


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def summary_of(result) -> dict:
    assert result.exit_code == 0, (result.stdout, result.stderr)
    return json.loads(result.stdout)


def assert_clean_failure(result, code, match):
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr + result.stdout
    if code == 1:
        lines = [ln for ln in result.stderr.splitlines() if ln.strip()]
        assert len(lines) == 1 and lines[0].startswith("Error: "), result.stderr
        assert match in lines[0], lines[0]
    else:
        assert match in result.stderr, result.stderr


def digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


def raw(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def metres(path: Path) -> np.ndarray:
    """A KITTI depth PNG in metres, decoded here (value / 256)."""
    img = raw(path)
    assert img.dtype == np.uint16
    return img.astype(np.float32) / np.float32(256)


def kitti_png(depth: np.ndarray) -> np.ndarray:
    q = np.clip(np.rint(depth.astype(np.float64) * 256.0), 1, 65535)
    return np.where(depth > 0, q, 0).astype(np.uint16)


@pytest.fixture(scope="module")
def sparse(tmp_path_factory) -> Path:
    """The sample scans projected at half size (621x188): a ``project`` output folder."""
    out = tmp_path_factory.mktemp("sparse") / "depth"
    r = run("project", SYNTH / "velodyne", "--calib", SYNTH / "calib", "--image-size",
            "1242x375", "--resize", "0.5", "-o", out)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    return out


SETTINGS = [
    ([], DensifySettings()),
    (["--variant", "bilateral", "--no-extrapolate"],
     DensifySettings(variant="bilateral", extrapolate=False)),
    (["--multiscale"], DensifySettings(multiscale=True)),
    (["--multiscale", "--variant", "bilateral", "--inversion-offset", "60"],
     DensifySettings(multiscale=True, variant="bilateral", max_depth=60.0)),
    (["--method", "nearest"], DensifySettings(method="nearest")),
    (["--method", "linear", "--outside", "zero"], DensifySettings(method="linear", outside="zero")),
]  # fmt: skip


@pytest.mark.parametrize(
    "args, settings", SETTINGS, ids=lambda v: " ".join(v) if isinstance(v, list) else ""
)
def test_output_is_the_library_result(sparse, tmp_path, args, settings):
    out = tmp_path / "dense"
    s = summary_of(run("densify", sparse, "-o", out, *args, "--json"))
    assert s["frames"] == s["processed"] == 3 and s["method"] == settings.method
    measured, filled = [], []
    for f in FRAMES:
        depth = metres(sparse / f"{f}.png")
        res = densify(depth, settings)
        np.testing.assert_array_equal(raw(out / f"{f}.png"), kitti_png(res.depth))
        mask = raw(out / "mask" / f"{f}.png")
        assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
        np.testing.assert_array_equal(mask == 255, depth > 0)
        measured.append(np.mean(depth > 0))
        filled.append(np.mean((res.depth > 0) & (depth == 0)))
    assert s["measured_pct"] == pytest.approx(100 * np.mean(measured), abs=1e-4)
    assert s["filled_pct"] == pytest.approx(100 * np.mean(filled), abs=1e-4)
    assert s["seconds_per_frame"] > 0


def test_npy_format_is_exact_float_metres(sparse, tmp_path):
    out = tmp_path / "dense"
    s = summary_of(run("densify", sparse, "-o", out, "--format", "npy", "--json"))
    assert s["processed"] == 3
    for f in FRAMES:
        got = np.load(out / f"{f}.npy")
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, densify(metres(sparse / f"{f}.png")).depth)
        assert (out / "mask" / f"{f}.png").is_file()


def test_reads_a_project_folder_through_its_record(sparse, tmp_path):
    """The project folder also holds calib/<frame>.json: only its depth maps are frames."""
    out = tmp_path / "dense"
    s = summary_of(run("densify", sparse, "-o", out, "--json"))
    assert s["frames"] == 3
    assert sorted(digest(out)) == sorted(
        [f"{f}.png" for f in FRAMES] + [f"mask/{f}.png" for f in FRAMES]
    )
    # the dense folder is itself an input of the role depth (its masks are not frames)
    again = summary_of(
        run("densify", out, "-o", tmp_path / "twice", "--method", "nearest", "--json")
    )
    assert again["frames"] == 3 and again["filled_pct"] == 0.0  # nothing left to fill


def test_kitti_depth_completion_tree_keeps_the_drives(sparse, tmp_path):
    tree = tmp_path / "data_depth_velodyne"
    drives = ("2011_09_26_drive_0001_sync", "2011_09_26_drive_0002_sync")
    for split, drive in zip(("train", "val"), drives, strict=True):
        d = tree / split / drive / "proj_depth" / "velodyne_raw" / "image_02"
        d.mkdir(parents=True)
        for f in FRAMES[:2]:
            shutil.copy(sparse / f"{f}.png", d / f"00000{f}.png")
    out = tmp_path / "dense"
    s = summary_of(run("densify", tree, "-o", out, "--json"))
    assert s["frames"] == 4
    for drive in drives:
        for f in FRAMES[:2]:
            expected = kitti_png(densify(metres(sparse / f"{f}.png")).depth)
            np.testing.assert_array_equal(raw(out / drive / f"00000{f}.png"), expected)
            assert (out / "mask" / drive / f"00000{f}.png").is_file()


def test_radar_nearest_fill_against_brute_force(tmp_path):
    radar = tmp_path / "radar"
    r = run("project", SYNTH / "radar" / "000000.pcd", "--calib",
            SYNTH / "calib_radar" / "000000.json", "--resize", "0.25", "-o", radar)  # fmt: skip
    assert r.exit_code == 0, r.stderr
    s = summary_of(run("densify", radar, "-o", tmp_path / "dense", "--method", "nearest", "--json"))
    depth = metres(radar / "000000.png")
    v, u = np.nonzero(depth)
    assert 10 < v.size < 200  # a few dozen radar returns
    got = metres(tmp_path / "dense" / "000000.png")
    yy, xx = np.mgrid[: depth.shape[0], : depth.shape[1]]
    d2 = (yy.reshape(-1, 1) - v) ** 2 + (xx.reshape(-1, 1) - u) ** 2  # (pixels, points)
    nearest = d2 == d2.min(axis=1, keepdims=True)
    allowed = np.where(nearest, depth[v, u][None, :], np.nan)
    ok = np.any(np.abs(allowed - got.reshape(-1, 1)) <= 1 / 512, axis=1)
    assert ok.all() and s["empty_pct"] == 0.0
    assert s["measured_pct"] == pytest.approx(100 * v.size / depth.size, abs=1e-4)


def test_two_workers_write_the_same_bytes(sparse, tmp_path):
    assert run("densify", sparse, "-o", tmp_path / "a", "--workers", 1).exit_code == 0
    assert run("densify", sparse, "-o", tmp_path / "b", "--workers", 2).exit_code == 0
    a, b = digest(tmp_path / "a"), digest(tmp_path / "b")
    assert len(a) == 6 and a == b


def test_text_summary(sparse, tmp_path):
    r = run("densify", sparse, "-o", tmp_path / "dense")
    assert r.exit_code == 0, r.stderr
    assert r.stdout.startswith(f"dense depth maps in {tmp_path / 'dense'}")
    assert "filled pct" in r.stdout and "seconds per frame" in r.stdout


# -- bad input ----------------------------------------------------------------------------------


def test_8_bit_png_is_refused(tmp_path):
    bad = tmp_path / "in" / "000000.png"
    bad.parent.mkdir()
    cv2.imwrite(str(bad), np.full((20, 30), 7, np.uint8))
    r = run("densify", bad.parent, "-o", tmp_path / "out")
    assert_clean_failure(r, 1, "8-bit files cannot hold metric depth")
    assert not any((tmp_path / "out").rglob("*.png"))


@pytest.mark.parametrize(
    "args, code, match",
    [
        (["--inversion-offset", "0.1"], 1, "--inversion-offset: must be a finite number > 0.2"),
        (["--inversion-offset", "-3"], 2, "--inversion-offset"),
        (["--max-depth", "-3"], 2, "--max-depth"),
        (["--method", "kriging"], 2, "--method"),
        (["--format", "parquet"], 2, "--format"),
    ],
)
def test_bad_options(sparse, tmp_path, args, code, match):
    r = run("densify", sparse, "-o", tmp_path / "out", *args)
    assert_clean_failure(r, code, match)
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.png"))


def test_same_frame_twice(sparse, tmp_path):
    r = run("densify", sparse / "000000.png", sparse / "000000.png", "-o", tmp_path / "out")
    assert_clean_failure(r, 1, "are the same frame '000000'")


def test_folder_without_depth_maps(tmp_path):
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "notes.txt").write_text("x")
    r = run("densify", tmp_path / "in", "-o", tmp_path / "out")
    assert_clean_failure(r, 1, "no *.png/*.npy files in")
