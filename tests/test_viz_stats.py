"""``viz`` pictures and ``stats`` numbers: library functions and commands."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.errors import ParameterError
from sparsetools.io.image import read_depth_png, read_image, write_depth_png, write_image
from sparsetools.ops.colormap import colorize_depth, overlay_depth
from sparsetools.ops.stats import depth_stats
from sparsetools.ops.viz import colorbar, depth_panels, label_panel

REAL = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "real"


def run(args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


# -- stats ---------------------------------------------------------------------------------------------
def test_depth_stats_against_reference():
    rng = np.random.default_rng(0)
    d = np.where(rng.random((30, 50)) < 0.1, rng.uniform(0.5, 90, (30, 50)), 0).astype(np.float32)
    d[0, 0] = np.nan
    d[0, 1] = -3.0
    d[29, 49] = np.inf
    s = depth_stats(d)
    valid = [float(v) for v in d.ravel() if math.isfinite(v) and v > 0]
    assert s["points"] == len(valid) and s["pixels"] == 1500
    assert s["density_percent"] == pytest.approx(100 * len(valid) / 1500)
    assert s["min"] == pytest.approx(min(valid)) and s["max"] == pytest.approx(max(valid))
    assert s["median"] == pytest.approx(
        sorted(valid)[len(valid) // 2]
        if len(valid) % 2
        else (sorted(valid)[len(valid) // 2 - 1] + sorted(valid)[len(valid) // 2]) / 2
    )
    empty = depth_stats(np.zeros((4, 4)))
    assert empty["points"] == 0 and empty["min"] is None and empty["density_percent"] == 0.0
    with pytest.raises(ParameterError):
        depth_stats(np.zeros(5))


def test_stats_intrinsic_error_hand_computed(tmp_path):
    exp = np.zeros((2, 4), np.float32)
    ref = np.zeros((2, 4), np.float32)
    exp[0, :] = [10, 10, 10, 10]
    ref[0, :] = [10, 12.5, 20, 90]  # ratios 1, 1.25 (not < 1.25), 2; 90 m is beyond 80 m
    exp[1, 0] = 5  # no reference there
    ref[1, 1] = 5  # no evaluated value there
    np.save(tmp_path / "f.npy", exp)
    (tmp_path / "ref").mkdir()
    np.save(tmp_path / "ref" / "f.npy", ref)
    res = run(["stats", tmp_path / "f.npy", "--reference", tmp_path / "ref", "--json"])
    assert res.exit_code == 0, res.output
    f = json.loads(res.stdout)["frames"][0]
    assert f["evaluated"] == 3 and f["points"] == 5
    assert "density" not in f  # one name, one unit: the manifest's density is a fraction
    assert f["density_percent"] == pytest.approx(100 * 5 / 8)
    assert f["delta1"] == pytest.approx(1 / 3)
    assert f["delta2"] == pytest.approx(2 / 3)  # 1.25 < 1.5625, 2 is not
    assert f["rmse"] == pytest.approx(math.sqrt((0 + 2.5**2 + 10**2) / 3))
    res = run(
        [
            "stats",
            tmp_path / "f.npy",
            "--reference",
            tmp_path / "ref",
            "--max-depth",
            "15",
            "--json",
        ]
    )
    assert json.loads(res.stdout)["frames"][0]["evaluated"] == 2
    text = run(["stats", tmp_path / "f.npy", "--reference", tmp_path / "ref"]).stdout
    assert "evaluated" in text and "0.3333" in text


def write_maps(folder: Path, maps: dict[str, np.ndarray], suffix=".png"):
    folder.mkdir(parents=True, exist_ok=True)
    for name, d in maps.items():
        if suffix == ".png":
            write_depth_png(folder / f"{name}.png", d)
        else:
            np.save(folder / f"{name}.npy", d.astype(np.float32))


def test_stats_command_folder_with_reference(tmp_path):
    rng = np.random.default_rng(1)
    lidar = {
        f"{i:02d}": np.where(rng.random((20, 30)) < 0.3, rng.uniform(2, 70, (20, 30)), 0)
        for i in range(3)
    }
    radar = {k: np.where(rng.random((20, 30)) < 0.5, v * 1.1, 0) for k, v in lidar.items()}
    write_maps(tmp_path / "lidar", lidar)
    write_maps(tmp_path / "radar", radar, suffix=".npy")
    res = run(["stats", tmp_path / "radar", "--reference", tmp_path / "lidar", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert [f["id"] for f in out["frames"]] == ["00", "01", "02"]
    for f in out["frames"]:
        exp = np.load(tmp_path / "radar" / f"{f['id']}.npy")
        ref = read_depth_png(tmp_path / "lidar" / f"{f['id']}.png")
        both = (exp > 0) & (ref > 0) & (ref <= 80)
        ratio = np.maximum(exp[both] / ref[both], ref[both] / exp[both])
        assert f["points"] == np.count_nonzero(exp)
        assert f["delta1"] == pytest.approx(np.mean(ratio < 1.25))
        assert f["rmse"] == pytest.approx(np.sqrt(np.mean((exp[both] - ref[both]) ** 2)), rel=1e-6)
    agg = out["aggregate"]
    assert agg["frames"] == 3
    assert agg["rmse"] == pytest.approx(np.mean([f["rmse"] for f in out["frames"]]))
    assert agg["total_points"] == sum(f["points"] for f in out["frames"])
    text = run(["stats", tmp_path / "radar", "--reference", tmp_path / "lidar"])
    assert text.exit_code == 0 and "delta1" in text.stdout and "mean of 3" in text.stdout


def test_stats_single_file_and_errors(tmp_path):
    d = np.zeros((10, 10))
    d[2, 3] = 12.0
    write_maps(tmp_path, {"one": d})
    res = run(["stats", tmp_path / "one.png", "--json"])
    out = json.loads(res.stdout)
    assert out["frames"][0]["points"] == 1 and out["frames"][0]["max"] == 12.0
    write_maps(tmp_path / "ref", {"one": np.ones((11, 10))})
    res = run(["stats", tmp_path / "one.png", "--reference", tmp_path / "ref"])
    assert res.exit_code == 1 and "11" in res.stderr and "Traceback" not in res.output
    write_image(tmp_path / "rgb.png", np.zeros((10, 10, 3), np.uint8))
    res = run(["stats", tmp_path / "rgb.png"])
    assert res.exit_code == 1 and "uint16" in res.stderr  # 8-bit PNG is not depth
    res = run(["stats", tmp_path / "one.png", "--reference", tmp_path / "nope"])
    assert res.exit_code == 2


# -- viz -----------------------------------------------------------------------------------------------
def test_label_panel_draws_text_in_corner_only():
    img = np.full((60, 200, 3), 100, np.uint8)
    out = label_panel(img, "raw radar")
    changed = np.any(out != img, axis=2)
    assert changed.any()
    ys, xs = np.nonzero(changed)
    assert ys.max() < 30 and xs.min() < 20
    assert np.array_equal(label_panel(img, ""), img)
    assert np.array_equal(img, np.full((60, 200, 3), 100, np.uint8))  # input untouched


def test_colorbar_uses_the_depth_colours():
    bar = colorbar(300, max_depth=80)
    assert bar.dtype == np.uint8 and bar.shape[1] == 300
    # the bar's first row, inside the margins, holds the turbo colours from 0 to 80 m
    row = bar[0]
    coloured = np.nonzero(np.any(row != 255, axis=1))[0]
    inner = coloured.max() - coloured.min() + 1
    ramp = np.linspace(0, 80, inner)
    ramp[0] = 1e-6
    np.testing.assert_array_equal(
        row[coloured.min() : coloured.max() + 1],
        colorize_depth(ramp[None].astype(np.float32), max_depth=80)[0],
    )
    with pytest.raises(ParameterError):
        colorbar(5)


def test_depth_panels_single_and_stacked():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (40, 80, 3), dtype=np.uint8)
    d = np.zeros((40, 80), np.float32)
    d[10, 20] = 5.0
    d[30, 60] = 70.0
    one = depth_panels(img, [d], max_depth=80, dilate=1, with_colorbar=False)
    np.testing.assert_array_equal(one, overlay_depth(img, d, max_depth=80, dilate=1))
    three = depth_panels(img, [d, d * 0.5, d * 0], labels=["a", "b", "c"], with_colorbar=False)
    assert three.shape == (3 * 40 + 2 * 4, 80, 3)
    wide = depth_panels(img, [d, d], vertical=False, with_colorbar=True)
    assert wide.shape[1] == 2 * 80 + 4 and wide.shape[0] > 40
    black = depth_panels(None, [d], dilate=0, with_colorbar=False)
    assert black[0, 0].tolist() == [0, 0, 0] and black[10, 20].tolist() != [0, 0, 0]
    with pytest.raises(ParameterError, match="one shape"):
        depth_panels(img, [d, np.zeros((41, 80))])
    with pytest.raises(ParameterError, match="label"):
        depth_panels(img, [d], labels=["a", "b"])
    with pytest.raises(ParameterError, match="image: is .* one shape"):
        depth_panels(img[:30], [d])


def test_viz_command(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (48, 96, 3), dtype=np.uint8)
    write_image(tmp_path / "img.png", img)
    maps = {}
    for name in ("b1", "b4", "b16"):
        d = np.where(rng.random((48, 96)) < 0.05, rng.uniform(1, 80, (48, 96)), 0)
        (tmp_path / name).mkdir()
        write_depth_png(tmp_path / name / "000000.png", d)
        maps[name] = tmp_path / name / "000000.png"
    out = tmp_path / "one.png"
    res = run(
        [
            "viz",
            maps["b1"],
            "--image",
            tmp_path / "img.png",
            "-o",
            out,
            "--no-colorbar",
            "--dilate",
            "0",
        ]
    )
    assert res.exit_code == 0, res.output
    expect = overlay_depth(img, read_depth_png(maps["b1"]), max_depth=80, dilate=0)
    np.testing.assert_array_equal(read_image(out), expect)
    res = run(
        [
            "viz",
            "--side-by-side",
            maps["b1"],
            maps["b4"],
            maps["b16"],
            "--image",
            tmp_path / "img.png",
            "-o",
            tmp_path / "cmp.png",
            "--labels",
            "1 beam,4 beams,16 beams",
        ]
    )
    assert res.exit_code == 0, res.output
    pic = read_image(tmp_path / "cmp.png")
    assert pic.shape[1] == 96 and pic.shape[0] > 3 * 48
    # refuses to overwrite, wrong label count, size mismatch, 8-bit depth
    assert run(["viz", maps["b1"], "-o", out]).exit_code == 1
    assert (
        run(["viz", maps["b1"], maps["b4"], "--labels", "x", "-o", tmp_path / "x.png"]).exit_code
        == 2
    )
    write_image(tmp_path / "small.png", img[:10])
    res = run(["viz", maps["b1"], "--image", tmp_path / "small.png", "-o", tmp_path / "y.png"])
    assert (
        res.exit_code == 1 and "Traceback" not in res.output and not (tmp_path / "y.png").exists()
    )
    res = run(["viz", tmp_path / "img.png", "-o", tmp_path / "z.png"])
    assert res.exit_code == 1 and not (tmp_path / "z.png").exists()


@pytest.mark.real
def test_real_kitti_gt_stats_and_picture(tmp_path):
    src = REAL / "kitti-depth-gt-metric3d"
    if not src.is_dir():
        pytest.skip(f"real data not present at {REAL}")
    res = run(["stats", src / "depth", "--json"])
    out = json.loads(res.stdout)
    assert len(out["frames"]) == 3
    for f in out["frames"]:
        # 19.50, 20.64 and 18.27 % (the README says ~19.5-20.6 %; frame 100 is lower)
        assert 18.0 < f["density_percent"] < 21.0
        assert 5.0 < f["min"] and f["max"] < 85.0
    # a map against itself: perfect intrinsic error
    res = run(["stats", src / "depth", "--reference", src / "depth", "--json"])
    agg = json.loads(res.stdout)["aggregate"]
    assert agg["delta1"] == 1.0 and agg["rmse"] == 0.0
    res = run(
        [
            "viz",
            src / "depth" / "0000000005.png",
            "--image",
            src / "rgb" / "0000000005.png",
            "-o",
            tmp_path / "v.png",
        ]
    )
    assert res.exit_code == 0 and read_image(tmp_path / "v.png").shape[1] == 1242
