"""Commands lowlight-synth, equalize and underwater on the synthetic scene."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.image import read_image, write_image


def run(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def _hashes(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


def _one_error_line(r, code=1):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("Error")
    return lines[-1]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from sparsetools.synth import generate_scene

    out = tmp_path_factory.mktemp("scene")
    generate_scene(out, seed=2, frames=3, width=200, height=64, underwater_frames=40)
    return out


@pytest.fixture(scope="module")
def night(scene, tmp_path_factory):
    out = tmp_path_factory.mktemp("night") / "n1"
    r = run("lowlight-synth", scene / "image_2", "--depth", scene / "depth_gt", "--calib",
            scene / "calib", "-o", out, "--variants", "2", "--seed", "4", "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    return out, json.loads(r.stdout)


# ----------------------------------------------------------------- lowlight-synth


def test_lowlight_synth_writes_images_records_and_manifest(scene, night):
    import pyarrow.parquet as pq

    from sparsetools.io.image import read_depth_png
    from sparsetools.ops.lowlight import lowlight

    out, summary = night
    assert summary["processed"] == 3 and summary["images"] == 6 and summary["manifest_rows"] == 6
    stems = sorted(p.stem for p in (scene / "image_2").glob("*.png"))
    for s in stems:
        for k in range(2):
            assert (out / f"{s}_v{k}.png").is_file()
            assert (out / "records" / f"{s}_v{k}.json").is_file()
    table = pq.read_table(out / "manifest.parquet").to_pylist()
    assert [(r["frame_id"], r["variant"]) for r in table] == [
        (s, k) for s in stems for k in range(2)
    ]
    for row in table:
        assert row["seed"] == 4 and row["flare_source"] == "depth" and row["camera"] == "SonyA7S2"
        depth = read_depth_png(row["depth"])
        assert all(0 < d <= 20 for d in row["flare_depth"])
        assert all(
            0 < depth[v, u] <= 20 for u, v in zip(row["flare_u"], row["flare_v"], strict=True)
        )
        assert 0.4 <= row["brightness"] <= 1.0 and 1.8 <= row["gamma"] <= 2.2
        # The manifest alone reproduces the image exactly.
        again, _ = lowlight(read_image(row["source"]), record=json.loads(row["record_json"]))
        np.testing.assert_array_equal(again, read_image(out / row["output"]))


def test_workers_give_identical_bytes(scene, night, tmp_path):
    out, _ = night
    other = tmp_path / "n2"
    r = run("lowlight-synth", scene / "image_2", "--depth", scene / "depth_gt", "--calib",
            scene / "calib", "-o", other, "--variants", "2", "--seed", "4",
            "--workers", "2")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert _hashes(other) == _hashes(out)


def test_resume_recomputes_only_missing_outputs(scene, tmp_path):
    out = tmp_path / "n"
    args = ["lowlight-synth", scene / "image_2", "-o", out, "--seed", "1", "--json"]
    assert run(*args).exit_code == 0
    before = _hashes(out)
    victim = sorted(out.glob("*.png"))[1]
    victim.unlink()
    (out / "manifest.parquet").unlink()
    r = run(*args)
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    assert s["processed"] == 1 and s["skipped_existing"] == 2 and s["manifest_rows"] == 3
    assert _hashes(out) == before


def test_other_settings_are_not_mixed_into_an_output(scene, tmp_path):
    out = tmp_path / "n"
    assert run("lowlight-synth", scene / "image_2", "-o", out, "--no-flare").exit_code == 0
    r = run("lowlight-synth", scene / "image_2", "-o", out)
    assert "made with --flare off, not on: use --overwrite" in _one_error_line(r)
    # Other variants write other file names: still refused (the folder would mix runs).
    r = run("lowlight-synth", scene / "image_2", "-o", out, "--no-flare", "--variants", "2")
    assert "made with --variants 1, not 2" in _one_error_line(r)
    assert not list(out.glob("*_v1.png"))
    r = run("lowlight-synth", scene / "image_2", "-o", out, "--overwrite", "--noise", "none")
    assert r.exit_code == 0, r.output


def test_options_reach_the_records(scene, tmp_path):
    import pyarrow.parquet as pq

    out = tmp_path / "n"
    r = run("lowlight-synth", scene / "image_2", "-o", out, "--flare-count", "2", "--noise",
            "gaussian", "--camera", "NikonD850", "--brightness", "0.5,0.5",
            "--gamma", "2,2")  # fmt: skip
    assert r.exit_code == 0, r.output
    for row in pq.read_table(out / "manifest.parquet").to_pylist():
        assert row["flare_count"] == 2 and row["flare_source"] == "uniform"
        assert row["noise_model"] == "gaussian" and row["camera"] == "NikonD850"
        assert row["brightness"] == 0.5 and row["gamma"] == 2.0


def test_lowlight_bad_input(scene, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    shutil.copy(scene / "depth_gt" / "000000.png", src / "000000.png")  # a 16-bit depth map
    before = _hashes(src)
    out = tmp_path / "out"
    line = _one_error_line(run("lowlight-synth", src, "-o", out))
    assert "uint16" in line and "8-bit" in line
    assert not list(out.glob("*.png")) and not (out / "manifest.parquet").exists()
    assert _hashes(src) == before
    # Inverted range, flare count 0: usage errors (exit 2).
    for opt in (["--brightness", "0.9,0.5"], ["--gamma", "2.2,1.8"], ["--flare-count", "0,3"],
                ["--ratio", "-1,2"]):  # fmt: skip
        r = run("lowlight-synth", scene / "image_2", "-o", out, *opt)
        assert r.exit_code == 2 and "Traceback" not in r.output, opt
    # A depth folder lacking one stem, and a depth map of another size.
    depth = tmp_path / "depth"
    depth.mkdir()
    shutil.copy(scene / "depth_gt" / "000000.png", depth / "000000.png")
    assert "no depth map" in _one_error_line(
        run("lowlight-synth", scene / "image_2", "--depth", depth, "-o", out)
    )
    img = tmp_path / "one"
    img.mkdir()
    write_image(img / "000000.png", np.zeros((30, 50, 3), np.uint8))
    line = _one_error_line(run("lowlight-synth", img, "--depth", depth, "-o", out))
    assert "50x30" in line and "200x64" in line
    assert not list(out.glob("*.png"))


def _eld_json() -> dict:
    """The shipped ELD tables, read as plain JSON (independently of sparsetools.ops.noise)."""
    from importlib.resources import files

    doc = json.loads((files("sparsetools") / "data" / "eld_cameras.json").read_text("utf-8"))
    return doc["cameras"]


def test_every_eld_camera_is_offered_and_color_bias_reaches_the_manifest(scene, tmp_path):
    import pyarrow.parquet as pq

    from sparsetools.ops.lowlight import LowLightRecord, lowlight

    tables = _eld_json()
    r = run("lowlight-synth", "--help")
    assert all(name in r.output for name in tables) and "random" in r.output
    out = tmp_path / "n"
    r = run("lowlight-synth", scene / "image_2", "-o", out, "--camera", "CanonEOS5D4",
            "--color-bias", "--no-flare", "--seed", "2")  # fmt: skip
    assert r.exit_code == 0, r.output
    table = pq.read_table(out / "manifest.parquet")
    import pyarrow as pa

    assert pa.types.is_list(table.schema.field("color_bias").type)
    assert table.schema.field("color_bias").type.value_type == pa.float64()
    assert table.schema.field("noise_table_row").type == pa.int32()
    entry = tables["CanonEOS5D4"]
    rows = table.to_pylist()
    for row in rows:
        k = row["noise_table_row"]
        assert 0 <= k < len(entry["G_shape"]) and row["camera"] == "CanonEOS5D4"
        assert row["tukey_lambda"] == entry["G_shape"][k]
        r_, g1, b, g2 = entry["color_bias"][k]
        assert row["color_bias"] == pytest.approx([r_, (g1 + g2) / 2, b], rel=1e-12)
        rec = LowLightRecord.from_json(row["record_json"])
        # Nothing the record's summary holds is dropped from the manifest.
        assert set(rec.summary()) <= set(table.column_names)
        assert {k: row[k] for k in rec.summary()} == rec.summary()
        night, _ = lowlight(read_image(row["source"]), record=rec)
        np.testing.assert_array_equal(night, read_image(out / row["output"]))
    assert len({row["noise_table_row"] for row in rows}) > 1 or len(rows) < 3
    # Without --color-bias the same draws carry no offset (and are another run's settings).
    plain = tmp_path / "p"
    assert run("lowlight-synth", scene / "image_2", "-o", plain, "--camera", "CanonEOS5D4",
               "--no-flare", "--seed", "2").exit_code == 0  # fmt: skip
    for a, b in zip(rows, pq.read_table(plain / "manifest.parquet").to_pylist(), strict=True):
        assert b["color_bias"] == [0.0, 0.0, 0.0] and b["noise_table_row"] == a["noise_table_row"]
    line = _one_error_line(
        run(
            "lowlight-synth",
            scene / "image_2",
            "-o",
            plain,
            "--camera",
            "CanonEOS5D4",
            "--no-flare",
            "--seed",
            "2",
            "--color-bias",
        )
    )
    assert "made with --color-bias off, not on" in line


def test_grey_input_is_converted(tmp_path):
    import cv2

    src = tmp_path / "grey.png"
    cv2.imwrite(str(src), np.full((20, 30), 128, np.uint8))
    r = run("lowlight-synth", src, "-o", tmp_path / "out", "--noise", "none", "--no-flare")
    assert r.exit_code == 0, r.output
    out = read_image(tmp_path / "out" / "grey.png")
    assert out.shape == (20, 30, 3) and np.all(out[..., 0] == out[..., 1])


# ----------------------------------------------------------------- equalize


def test_equalize_uses_one_lut_for_all_frames(night, tmp_path):
    from sparsetools.ops.enhance import apply_lut, mcie_lut

    src, _ = night
    out = tmp_path / "eq"
    ref = sorted(src.glob("*.png"))[2]
    r = run("equalize", src, "-o", out, "--reference-frame", ref.stem, "--clip", "0.008", "--json")
    assert r.exit_code == 0, r.output
    lut = mcie_lut(read_image(ref), clip=0.008)
    doc = json.loads((out / "mcie_lut.json").read_text())
    assert doc["lut"] == [lut[:, c].tolist() for c in range(3)] and doc["reference"] == str(ref)
    for f in sorted(src.glob("*.png")):
        np.testing.assert_array_equal(read_image(out / f.name), apply_lut(read_image(f), lut))
    # Default reference: the first frame; another table in the same folder is refused.
    line = _one_error_line(run("equalize", src, "-o", out))
    assert "equalised frames made with --clip 0.008, not 0.004" in line
    line = _one_error_line(run("equalize", src, "-o", out, "--clip", "0.008"))
    assert (
        f"made with --reference-frame {ref.resolve()}, not {sorted(src.glob('*.png'))[0].resolve()}"
        in line
    )
    assert run("equalize", src, "-o", out, "--overwrite").exit_code == 0
    first = sorted(src.glob("*.png"))[0]
    assert json.loads((out / "mcie_lut.json").read_text())["reference"] == str(first)


def rnw_lut_reference(image: np.ndarray, clip: float) -> np.ndarray:
    """RNW's released MCIE arithmetic as issue 17 describes it, in Python integers: the clip
    limit truncated to an integer, the excess spread as round(excess / 256) whole pixels per
    bin, the table values truncated to uint8."""
    n = image.shape[0] * image.shape[1]
    limit = int(clip * n)
    lut = np.zeros((256, 3), np.uint8)
    for c in range(3):
        hist = [0] * 256
        for level, count in zip(*np.unique(image[:, :, c], return_counts=True), strict=True):
            hist[int(level)] = int(count)
        excess = sum(max(h - limit, 0) for h in hist)
        hist = [min(h, limit) + round(excess / 256) for h in hist]
        cdf, total = [], 0
        for h in hist:
            total += h
            cdf.append(total)
        lo = next(v for v in cdf if v > 0)
        for b in range(256):
            lut[b, c] = max(cdf[b] - lo, 0) * 255 // (cdf[-1] - lo) if cdf[-1] > lo else b
    return lut


def _check_rnw_equalize(images: list[Path], out: Path, clip: float) -> None:
    ref = rnw_lut_reference(read_image(images[0]), clip)
    doc = json.loads((out / "mcie_lut.json").read_text())
    assert doc["rounding"] == "rnw" and doc["clip"] == clip
    assert doc["lut"] == [ref[:, c].tolist() for c in range(3)]
    for f in images:
        img = read_image(f)
        expected = np.stack([ref[img[:, :, c], c] for c in range(3)], axis=2)
        np.testing.assert_array_equal(read_image(out / f.name), expected)


def test_equalize_rnw_rounding_equals_the_description(night, tmp_path):
    src, _ = night
    frames = sorted(src.glob("*.png"))
    out = tmp_path / "rnw"
    r = run("equalize", src, "-o", out, "--rounding", "rnw", "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["rounding"] == "rnw"
    _check_rnw_equalize(frames, out, 0.004)
    # The default is today's rounding; a rerun with the other one is refused, naming it.
    line = _one_error_line(run("equalize", src, "-o", out))
    assert "equalised frames made with --rounding rnw, not nearest: use --overwrite" in line
    near = tmp_path / "near"
    assert run("equalize", src, "-o", near).exit_code == 0
    doc = json.loads((near / "mcie_lut.json").read_text())
    rnw = json.loads((out / "mcie_lut.json").read_text())
    assert doc["rounding"] == "nearest"
    diff = np.asarray(doc["lut"], int) - np.asarray(rnw["lut"], int)
    assert set(np.unique(diff)) <= {0, 1} and diff.any()  # RNW's is at most one level lower


@pytest.mark.real
def test_equalize_rnw_rounding_on_real_kitti_images(kitti_object, tmp_path):
    frames = sorted((kitti_object / "image_2").glob("*.png"))
    out = tmp_path / "rnw"
    r = run("equalize", kitti_object / "image_2", "-o", out, "--rounding", "rnw", "--clip",
            "0.008")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert len(frames) >= 3
    _check_rnw_equalize(frames, out, 0.008)


def test_equalize_bad_input(scene, tmp_path):
    r = run("equalize", scene / "image_2", "-o", tmp_path / "o", "--clip", "0")
    assert r.exit_code == 2 and "Traceback" not in r.output
    line = _one_error_line(run("equalize", scene / "image_2", "-o", tmp_path / "o", "--reference-frame",
                               "nope"))  # fmt: skip
    assert "nope" in line
    line = _one_error_line(run("equalize", scene / "depth_gt", "-o", tmp_path / "o2"))
    assert "uint16" in line
    assert not list((tmp_path / "o2").glob("*.png"))


# ----------------------------------------------------------------- underwater


def test_underwater_matches_library_and_workers(scene, tmp_path):
    from sparsetools.ops.underwater import UnderwaterCompensator

    uw = scene / "underwater"
    a, b = tmp_path / "a", tmp_path / "b"
    r = run("underwater", uw / "seafloor", "--water", uw / "water", "-o", a, "--median-window", "11",
            "--json")  # fmt: skip
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["frames"] == 40 and summary["frames_processed"] == 40
    r = run("underwater", uw / "seafloor", "--water", uw / "water", "-o", b, "--median-window", "11",
            "--workers", "2")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert _hashes(a) == {k: v for k, v in _hashes(b).items()}
    frames = sorted((uw / "seafloor").glob("*.png"))
    water = [read_image(p) for p in sorted((uw / "water").glob("*.png"))]
    comp = UnderwaterCompensator(water, window=11)
    for f, (albedo, valid) in zip(frames, comp.process(read_image(p) for p in frames), strict=True):
        expected = np.clip(np.rint(albedo), 0, 255).astype(np.uint8)
        np.testing.assert_array_equal(read_image(a / f.name), expected)
        mask = read_image(a / "mask" / f.name)[..., 0]
        np.testing.assert_array_equal(mask > 0, valid)
    assert json.loads((a / "underwater.json").read_text())["a_ref_per_sequence"][""] == [
        float(v) for v in comp.a_ref
    ]


def test_underwater_recovers_generator_albedo(scene, tmp_path):
    """On the generator's files: the relative error to albedo.png falls (global factor fitted)."""
    uw = scene / "underwater"
    out = tmp_path / "o"
    assert run("underwater", uw / "seafloor", "--water", uw / "water", "-o", out, "--median-window",
               "15").exit_code == 0  # fmt: skip
    truth = json.loads((uw / "truth.json").read_text())
    albedo = read_image(uw / "albedo.png").astype(np.float64) / 255
    errs = {"before": [], "after": []}
    for rec in truth["seafloor"][7:-7]:  # centred windows
        name = f"{rec['index']:06d}.png"
        col = rec["albedo_offset"][1]
        t = albedo[:, col : col + 160]
        for key, img in (("before", uw / "seafloor" / name), ("after", out / name)):
            e = read_image(img).astype(np.float64)
            s = (e * t).sum(axis=(0, 1)) / (e * e).sum(axis=(0, 1))
            errs[key].append(np.sqrt(((s * e - t) ** 2).sum() / (t**2).sum()))
    before, after = np.median(errs["before"]), np.median(errs["after"])
    print(f"\nunderwater relative RMSE vs albedo.png: before {before:.3f} after {after:.3f}")
    assert after < 0.6 * before


def test_underwater_resume_and_settings(scene, tmp_path):
    uw = scene / "underwater"
    out = tmp_path / "o"
    args = [
        "underwater",
        uw / "seafloor",
        "--water",
        uw / "water",
        "-o",
        out,
        "--median-window",
        "5",
    ]
    assert run(*args).exit_code == 0
    before = _hashes(out)
    (out / "000020.png").unlink()
    r = run(*args, "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["frames_processed"] > 0
    assert _hashes(out) == before
    assert "made with --median-window 5, not 7" in _one_error_line(run(*args[:-1], "7"))


def test_underwater_bad_input(scene, tmp_path):
    uw = scene / "underwater"
    before = _hashes(uw)
    out = tmp_path / "o"
    line = _one_error_line(run("underwater", uw / "seafloor", "--water", uw / "water", "-o", out,
                               "--median-window", "41"))  # fmt: skip
    assert "fewer than the median window" in line
    empty = tmp_path / "empty"
    empty.mkdir()
    line = _one_error_line(run("underwater", uw / "seafloor", "--water", empty, "-o", out))
    assert "no water-only frames" in line
    r = run(
        "underwater", uw / "seafloor", "--water", uw / "water", "-o", out, "--median-window", "4"
    )
    assert r.exit_code == 2 and "odd" in r.output
    r = run("underwater", uw / "seafloor", "--water", uw / "water", "-o", out, "--a-ref", "1,-2,3")
    assert r.exit_code == 2
    assert not out.exists() or not list(out.glob("*.png"))
    assert _hashes(uw) == before
