"""Command dark-channel: outputs equal the library and a per-pixel reference, encodings,
pictures, workers, resume, a defocus-synth folder as input, bad input."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.image import read_image, write_image
from sparsetools.ops.dark_channel import dark_channel_features


def run(*args):
    return CliRunner().invoke(cli, ["-q", *map(str, args)])


def _hashes(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


def _grey(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None and img.ndim == 2, path
    return img


def _one_error_line(r, code=1):
    assert r.exit_code == code, r.output
    assert "Traceback" not in r.output
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert lines and lines[-1].startswith("Error")
    return lines[-1]


def ref_features(img: np.ndarray, n: int, t: float):
    """Dark channel, LDDCV (mean intensity) and norm mask, pixel by pixel, windows clipped."""
    unit = img.astype(np.float64) / 255
    h, w, _ = unit.shape
    half = n // 2
    dark = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            dark[y, x] = unit[
                max(y - half, 0) : y + half + 1, max(x - half, 0) : x + half + 1
            ].min()
    var = np.zeros((h, w, 2))
    for k, chan in enumerate((unit.mean(axis=2), dark)):
        for y in range(h):
            for x in range(w):
                for dy in (-1, 0, 1):
                    for dx in (-1, 0, 1):
                        if 0 <= y + dy < h and 0 <= x + dx < w:
                            diff = abs(chan[y, x] - chan[y + dy, x + dx])
                            var[y, x, k] = max(var[y, x, k], diff)
    mask = np.sqrt(var[..., 0] ** 2 + var[..., 1] ** 2) > t
    return dark, var, mask


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    """Two sequences of small images: smooth gradients with sharp blocks and noise."""
    root = tmp_path_factory.mktemp("dc_in") / "img"
    rng = np.random.default_rng(3)
    for seq in ("a", "b"):
        for i in range(2):
            base = np.linspace(20, 230, 33)[None, :, None] + rng.normal(0, 6, (21, 33, 3))
            base[5:12, 8:20] = rng.integers(0, 256, 3)
            write_image(root / seq / f"{i:06d}.png", np.clip(base, 0, 255).astype(np.uint8))
    return root


def test_outputs_equal_the_library_and_a_per_pixel_reference(images, tmp_path):
    out = tmp_path / "dc"
    r = run("dark-channel", images, "-o", out, "--patch-size", "5", "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert summary["frames"] == 4 and summary["processed"] == 4
    fractions = []
    for src in sorted(images.rglob("*.png")):
        rel = src.relative_to(images)
        img = read_image(src)
        f = dark_channel_features(img, window=5)
        dark = _grey(out / "dark" / rel)
        assert dark.dtype == np.uint8
        np.testing.assert_array_equal(dark, np.rint(f.dark * 255).astype(np.uint8))
        lddcv = np.load(out / "lddcv" / rel.with_suffix(".npy"))
        assert lddcv.dtype == np.float32 and lddcv.shape == (21, 33, 2)
        np.testing.assert_array_equal(lddcv, f.lddcv)
        mask = _grey(out / "mask" / rel)
        np.testing.assert_array_equal(mask, f.mask.astype(np.uint8) * 255)
        ref_dark, ref_var, ref_mask = ref_features(img, 5, 0.05)
        # 8-bit input: the dark channel is exactly one of its levels.
        np.testing.assert_array_equal(dark, np.rint(ref_dark * 255).astype(np.uint8))
        np.testing.assert_allclose(lddcv, ref_var, atol=1e-6)
        close = np.abs(np.hypot(ref_var[..., 0], ref_var[..., 1]) - 0.05) < 1e-6
        np.testing.assert_array_equal((mask > 0)[~close], ref_mask[~close])
        fractions.append(ref_mask.mean())
    assert summary["mask_fraction"] == pytest.approx(np.mean(fractions), abs=1e-3)
    assert not (out / "pictures").exists()


def test_png_encodings_separate_masks_and_pictures(images, tmp_path):
    out = tmp_path / "dc"
    r = run("dark-channel", images / "a", "-o", out, "--lddcv-format", "png", "--mask-mode",
            "separate", "--mask-threshold", "0.02", "--intensity", "luma",
            "--save-pictures")  # fmt: skip
    assert r.exit_code == 0, r.output
    for src in sorted((images / "a").glob("*.png")):
        img = read_image(src)
        f = dark_channel_features(img, threshold=0.02, intensity="luma", combine="separate")
        for k, c in enumerate(("y", "dc")):
            v = _grey(out / "lddcv" / f"{src.stem}_{c}.png")
            assert v.dtype == np.uint16
            np.testing.assert_allclose(v / 65535.0, f.lddcv[..., k], atol=0.5 / 65535 + 1e-7)
            m = _grey(out / "mask" / f"{src.stem}_{c}.png")
            np.testing.assert_array_equal(m > 0, f.mask[..., k])
            assert set(np.unique(m)) <= {0, 255}
        pic = read_image(out / "pictures" / f"{src.stem}.png")
        # image, dark channel, two LDDCV channels, two masks, stacked with 4 px gaps
        assert pic.shape == (6 * 21 + 5 * 4, 33, 3)
        np.testing.assert_array_equal(pic[21:25], 255)  # the first gap


def test_workers_give_identical_bytes(images, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert run("dark-channel", images, "-o", a, "--save-pictures").exit_code == 0
    r = run("dark-channel", images, "-o", b, "--save-pictures", "--workers", "2")
    assert r.exit_code == 0, r.output
    assert _hashes(a) == _hashes(b) and len(_hashes(a)) == 16


def test_reads_the_images_of_a_defocus_synth_folder(images, tmp_path):
    defocused = tmp_path / "defocus"
    depth = tmp_path / "depth"
    for src in images.rglob("*.png"):
        rel = src.relative_to(images).with_suffix(".npy")
        (depth / rel).parent.mkdir(parents=True, exist_ok=True)
        d = np.full((21, 33), 0.7, np.float32)
        d[:, 16:] = 3.0  # the right half out of focus
        np.save(depth / rel, d)
    r = run("defocus-synth", images, "--depth", depth, "-o", defocused, "--radius-format", "png")
    assert r.exit_code == 0, r.output
    out = tmp_path / "dc"
    r = run("dark-channel", defocused, "-o", out, "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["frames"] == 4  # not the radius PNGs
    names = sorted(p.relative_to(out / "dark").as_posix() for p in (out / "dark").rglob("*.png"))
    assert names == ["a/000000.png", "a/000001.png", "b/000000.png", "b/000001.png"]
    f = dark_channel_features(read_image(defocused / "b" / "000001.png"))
    np.testing.assert_array_equal(_grey(out / "mask" / "b" / "000001.png") > 0, f.mask)


def test_resume_and_settings(images, tmp_path):
    out = tmp_path / "dc"
    args = ["dark-channel", images, "-o", out, "--json"]
    assert run(*args).exit_code == 0
    before = _hashes(out)
    (out / "lddcv" / "b" / "000000.npy").unlink()
    s = json.loads(run(*args).stdout)
    assert s["processed"] == 1 and s["skipped_existing"] == 3
    assert _hashes(out) == before
    line = _one_error_line(run(*args, "--patch-size", "7"))
    assert "dark-channel maps made with --patch-size 15, not 7: use --overwrite" in line
    line = _one_error_line(run(*args, "--mask-threshold", "0.1"))
    assert "made with --mask-threshold 0.05, not 0.1" in line
    line = _one_error_line(run(*args, "--save-pictures"))
    assert "made with --save-pictures off, not on" in line
    assert _hashes(out) == before


def test_bad_input(images, tmp_path):
    out = tmp_path / "out"
    for opt, text in ((["--patch-size", "4"], "odd"), (["--patch-size", "0"], ">= 1"),
                      (["--window", "4"], "odd"),
                      (["--mask-threshold", "-1"], ">= 0"), (["--mask-mode", "all"], "all"),
                      (["--lddcv-format", "tif"], "tif")):  # fmt: skip
        r = run("dark-channel", images, "-o", out, *opt)
        assert r.exit_code == 2 and text in r.output and "Traceback" not in r.output, opt
    bad = tmp_path / "bad"
    bad.mkdir()
    cv2.imwrite(str(bad / "000000.png"), np.full((10, 12), 4000, np.uint16))
    before = _hashes(bad)
    line = _one_error_line(run("dark-channel", bad, "-o", out))
    assert "uint16 image, expected 8-bit RGB" in line
    assert not out.exists() or not list(out.rglob("*.png"))
    assert _hashes(bad) == before
