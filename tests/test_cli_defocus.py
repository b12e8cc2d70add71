"""Command defocus-synth: outputs equal the library, radius = formula, replay, workers, resume,
bad input."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.image import read_depth_png, read_image, write_image


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def _hashes(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


def _tree(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _one_error_line(r, code=1):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("Error")
    return lines[-1]


def formula_radius(depth, *, f, fn, pitch, focus):
    """r(d) = 1 / (sqrt(2) p) * (A f / (D - f)) * |d - D| / d, A = f / F_n, pixel by pixel;
    no depth = infinitely far."""
    out = np.empty(depth.shape)
    for idx, d in np.ndenumerate(depth.astype(np.float64)):
        rel = abs(d - focus) / d if (math.isfinite(d) and d > 0) else 1.0
        out[idx] = (f / fn) * f / ((focus - f) * math.sqrt(2) * pitch) * rel
    return out


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from sparsetools.synth import generate_scene

    out = tmp_path_factory.mktemp("scene")
    generate_scene(out, seed=2, frames=3, width=200, height=64, underwater_frames=0)
    return out


#: A 25 mm f/1.4-4 lens on 5 um pixels focused at 3-30 m: blur of a few pixels on the scene.
SAMPLED = ["--focal-length-mm", "25", "--pixel-pitch-um", "5", "--f-number", "1.4,4",
           "--focus-distance", "3,30", "--noise", "eld", "--camera", "NikonD850",
           "--color-bias", "--missing-depth", "far", "--seed", "5"]  # fmt: skip


@pytest.fixture(scope="module")
def sampled(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("defocus") / "d1"
    r = run("defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "-o", out,
            *SAMPLED, "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    return out, json.loads(r.stdout)


def test_outputs_equal_the_library_and_replay_from_records(scene, sampled):
    import pyarrow.parquet as pq

    from sparsetools.ops.defocus import CameraOptics, DefocusParams, DefocusRecord, defocus
    from sparsetools.ops.noise import CAMERA_PROFILES
    from sparsetools.random import frame_rng

    out, summary = sampled
    assert summary["processed"] == 3 and summary["images"] == 3 and summary["manifest_rows"] == 3
    params = DefocusParams(
        camera=CameraOptics("lens", 25e-3, 1.4, 5e-6), focus_distance=(3.0, 30.0),
        f_number=(1.4, 4.0), missing="far", noise="eld", noise_camera="NikonD850",
        color_bias=True,
    )  # fmt: skip
    stems = sorted(p.stem for p in (scene / "image_2").glob("*.png"))
    rows = pq.read_table(out / "manifest.parquet").to_pylist()
    assert [r["frame_id"] for r in rows] == stems
    far = 0
    for stem, row in zip(stems, rows, strict=True):
        image = read_image(scene / "image_2" / f"{stem}.png")
        depth = read_depth_png(scene / "depth_gt" / f"{stem}.png")
        far += int(np.count_nonzero(depth == 0))
        blurred, radius, rec = defocus(image, depth, rng=frame_rng(5, stem), params=params)
        np.testing.assert_array_equal(read_image(out / f"{stem}.png"), blurred)
        np.testing.assert_array_equal(np.load(out / "radius" / f"{stem}.npy"), radius)
        side = json.loads((out / "records" / f"{stem}.json").read_text())
        mine = {k: v for k, v in side["record"].items() if k != "camera"}
        assert mine == {k: v for k, v in rec.to_dict().items() if k != "camera"}
        # The record alone replays the image exactly; the manifest row holds the same record.
        again, _, _ = defocus(image, depth, record=side["record"])
        np.testing.assert_array_equal(again, blurred)
        assert DefocusRecord.from_json(row["record_json"]) == DefocusRecord.from_dict(
            side["record"]
        )
        assert side["config"]["seed"] == 5 and side["frame_id"] == stem
        assert row["output"] == f"{stem}.png" and row["radius"] == f"radius/{stem}.npy"
        assert 1.4 <= row["f_number"] <= 4.0 and 3.0 <= row["focus_distance_m"] <= 30.0
        assert row["focal_length_m"] == pytest.approx(25e-3) and row["noise_camera"] == "NikonD850"
        assert row["color_bias"] == list(
            CAMERA_PROFILES["NikonD850"].rgb_bias(row["noise_table_row"])
        )
        assert row["radius_scale"] == pytest.approx(rec.radius_scale)
    # Sampled per frame: the three frames drew different focus distances.
    assert len({r["focus_distance_m"] for r in rows}) == 3
    assert summary["far_pixels"] == far > 0


def test_radius_map_equals_the_formula_in_both_encodings(tmp_path):
    rng = np.random.default_rng(0)
    src = tmp_path / "src"
    write_image(src / "img" / "a.png", rng.integers(0, 256, (20, 30, 3), dtype=np.uint8))
    depth = np.repeat(np.array([0.5, 1.0, 2.0, 5.0, 40.0, np.inf])[None], 5, axis=1)
    depth = np.repeat(depth, 20, axis=0)[:, :30].astype(np.float32)
    (src / "depth").mkdir()
    np.save(src / "depth" / "a.npy", depth)
    expected = formula_radius(depth, f=50e-3, fn=2.0, pitch=4.65e-6, focus=2.0)
    args = ["--depth", src / "depth", "--focal-length-mm", "50", "--f-number", "2",
            "--pixel-pitch-um", "4.65", "--focus-distance", "2", "--missing-depth", "far",
            "--max-radius", "8"]  # fmt: skip
    r = run("defocus-synth", src / "img", "-o", tmp_path / "npy", *args)
    assert r.exit_code == 0, r.output
    radius = np.load(tmp_path / "npy" / "radius" / "a.npy")
    assert radius.dtype == np.float32 and radius.shape == (20, 30)
    np.testing.assert_allclose(radius, expected, rtol=1e-6)
    assert radius[:, 10:15].max() == 0  # the focal plane (the clip radius does not apply)
    r = run("defocus-synth", src / "img", "-o", tmp_path / "png", *args, "--radius-format",
            "png", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    import cv2

    png = cv2.imread(str(tmp_path / "png" / "radius" / "a.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    # np.inf in a .npy is a hole: infinitely far, r(inf). The 0.5 m band (292 px) saturates.
    top = 65535 / 256
    np.testing.assert_allclose(png / 256.0, np.minimum(expected, top), atol=0.5 / 256 + 1e-9)
    summary = json.loads(r.stdout)
    assert summary["far_pixels"] == int(np.count_nonzero(~np.isfinite(depth)))
    assert summary["radius_saturated"] == int(np.count_nonzero(expected > top)) == 100


def test_a_plane_at_the_focus_distance_stays_sharp(tmp_path):
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    write_image(tmp_path / "a.png", image)
    np.save(tmp_path / "a.npy", np.full((24, 32), 0.7, np.float32))
    r = run("defocus-synth", tmp_path / "a.png", "--depth", tmp_path / "a.npy", "-o",
            tmp_path / "o")  # fmt: skip
    assert r.exit_code == 0, r.output
    np.testing.assert_array_equal(read_image(tmp_path / "o" / "a.png"), image)
    # 0.7 m is the default focus of the default preset (the paper's dfd-nyu camera).
    assert np.load(tmp_path / "o" / "radius" / "a.npy").max() < 1e-6  # float32 0.7 m


def test_focal_length_from_the_calibration(scene, tmp_path):
    from sparsetools.io.calib import load_calibration

    out = tmp_path / "o"
    r = run("defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "--calib",
            scene / "calib", "--pixel-pitch-um", "40", "--f-number", "1.4", "--focus-distance",
            "8", "--missing-depth", "far", "-o", out)  # fmt: skip
    assert r.exit_code == 0, r.output
    f_px = float(load_calibration(scene / "calib" / "000001.txt").K[0, 0])
    rec = json.loads((out / "records" / "000001.json").read_text())["record"]
    assert rec["focal_length_m"] == pytest.approx(f_px * 40e-6, rel=1e-12)
    depth = read_depth_png(scene / "depth_gt" / "000001.png")
    expected = formula_radius(depth, f=f_px * 40e-6, fn=1.4, pitch=40e-6, focus=8.0)
    np.testing.assert_allclose(np.load(out / "radius" / "000001.npy"), expected, rtol=1e-6)
    r = run("defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "--calib",
            scene / "calib", "--focal-length-mm", "4", "-o", tmp_path / "o2")  # fmt: skip
    assert r.exit_code == 2 and "not both" in r.output


def test_workers_give_identical_bytes(scene, sampled, tmp_path):
    out, _ = sampled
    other = tmp_path / "d2"
    r = run("defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "-o", other,
            *SAMPLED, "--workers", "2")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert _hashes(other) == _hashes(out)
    assert "manifest.parquet" in _hashes(out) and len(_hashes(out)) == 10


def test_resume_and_settings(scene, tmp_path):
    out = tmp_path / "o"
    args = ["defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "-o", out,
            "--missing-depth", "far", "--focus-distance", "2,20", "--json"]  # fmt: skip
    assert run(*args).exit_code == 0
    before = _hashes(out)
    (out / "radius" / "000001.npy").unlink()
    (out / "manifest.parquet").unlink()
    r = run(*args)
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["processed"] == 1 and s["skipped_existing"] == 2 and s["manifest_rows"] == 3
    assert _hashes(out) == before
    state = _tree(out)
    r = run(*args[:-1], "--blur-kernel", "gaussian")
    assert "defocused images made with --blur-kernel disk, not gaussian" in _one_error_line(r)
    r = run(*args[:-3], "--focus-distance", "3")
    assert "made with --focus-distance 2,20, not 3,3" in _one_error_line(r)
    assert _tree(out) == state


def test_bad_input(scene, tmp_path):
    src = tmp_path / "src"
    write_image(src / "img" / "000000.png", np.zeros((20, 30, 3), np.uint8))
    shutil.copytree(scene / "depth_gt", src / "depth")  # 200x64, with sky holes
    (src / "depth2").mkdir()
    shutil.copy(scene / "depth_gt" / "000000.png", src / "depth2" / "000000.png")
    before = _hashes(src)
    out = tmp_path / "out"
    line = _one_error_line(run("defocus-synth", src / "img", "--depth", src / "depth", "-o", out))
    assert "depth map is 200x64 but 000000.png is 30x20" in line
    assert not list(out.rglob("*.png")) and not (out / "manifest.parquet").exists()
    # Holes without --missing-depth far: refused with their count and the way out.
    line = _one_error_line(run("defocus-synth", scene / "image_2" / "000000.png", "--depth",
                               src / "depth" / "000000.png", "-o", out))  # fmt: skip
    holes = int(np.count_nonzero(read_depth_png(src / "depth" / "000000.png") == 0))
    assert f"no depth at {holes} of {64 * 200} pixels" in line and "--missing-depth far" in line
    assert not list(out.rglob("*.png"))
    # A depth folder lacking a frame; a focus distance inside the lens.
    line = _one_error_line(run("defocus-synth", scene / "image_2", "--depth", src / "depth2",
                               "-o", out))  # fmt: skip
    assert "no depth map" in line
    line = _one_error_line(
        run(
            "defocus-synth",
            scene / "image_2",
            "--depth",
            scene / "depth_gt",
            "--focal-length-mm",
            "50",
            "--focus-distance",
            "0.01",
            "-o",
            out,
        )
    )
    assert "must exceed the focal length" in line
    # Usage errors (exit 2): an unknown preset, an inverted range, a negative pitch.
    for opt in (["--sensor", "nope"], ["--focus-distance", "5,2"], ["--pixel-pitch-um", "-1"],
                ["--f-number", "0"], ["--noise", "poisson"]):  # fmt: skip
        r = run("defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "-o", out, *opt)
        assert r.exit_code == 2 and "Traceback" not in r.output, opt
    assert "'nope' is not one of" in run(
        "defocus-synth", scene / "image_2", "--depth", scene / "depth_gt", "-o", out, "--sensor",
        "nope",
    ).output  # fmt: skip
    assert not list(out.rglob("*.png")) and _hashes(src) == before
