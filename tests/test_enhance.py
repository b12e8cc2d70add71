"""MCIE: clipped histogram equalisation against independent references."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.enhance import apply_lut, mcie_lut


def _reference_lut(channel: np.ndarray, clip: float) -> list[int]:
    """Exact rational arithmetic, bin by bin, following RNW's description."""
    n = channel.size
    counts = [0] * 256
    for v in channel.ravel().tolist():
        counts[v] += 1
    limit = Fraction(clip) * n
    excess = sum(max(Fraction(c) - limit, 0) for c in counts)
    hist = [min(Fraction(c), limit) + excess / 256 for c in counts]
    cdf, acc = [], Fraction(0)
    for h in hist:
        acc += h
        cdf.append(acc)
    cdf_min = next(c for c in cdf if c > 0)
    cdf_max = cdf[-1]
    if cdf_max == cdf_min:
        return list(range(256))
    out = []
    for c in cdf:
        # Levels below the darkest one present have cdf < cdf_min: they map to 0.
        x = max(c - cdf_min, 0) / (cdf_max - cdf_min) * 255
        out.append(int(round(x)))  # Python rounds half to even, as numpy.rint does
    return out


def _images():
    rng = np.random.default_rng(0)
    dark = np.clip(rng.gamma(2.0, 8.0, (60, 80, 3)), 0, 255).astype(np.uint8)  # a night frame
    mid = rng.integers(90, 140, (33, 47, 3), dtype=np.uint8)  # low contrast
    spiky = np.zeros((40, 40, 3), np.uint8)
    spiky[:20] = 200
    spiky[20:, :5] = rng.integers(0, 256, (20, 5, 3), dtype=np.uint8)
    return [dark, mid, spiky]


@pytest.mark.parametrize("clip", [0.004, 0.008, 0.05, 1.0])
def test_lut_matches_exact_reference(clip):
    for img in _images():
        lut = mcie_lut(img, clip=clip)
        assert lut.shape == (256, 3) and lut.dtype == np.uint8
        for c in range(3):
            assert lut[:, c].tolist() == _reference_lut(img[:, :, c], clip)


def test_without_clipping_equals_opencv_equalize_hist():
    import cv2

    for img in _images():
        lut = mcie_lut(img, clip=1.0)
        for c in range(3):
            ch = np.ascontiguousarray(img[:, :, c])
            if len(np.unique(ch)) == 1:
                continue  # OpenCV returns the input for a constant image; so does the identity
            np.testing.assert_array_equal(apply_lut(ch, lut[:, c]), cv2.equalizeHist(ch))


def test_lut_properties():
    for img in _images():
        lut = mcie_lut(img).astype(int)
        assert np.all(np.diff(lut, axis=0) >= 0)  # monotone: order of grey levels is kept
        assert lut.max() == 255  # the brightest level maps to white
        # Clipping bounds the slope: a clipped bin holds at most limit + excess / 256 pixels.
        n = img.shape[0] * img.shape[1]
        for c in range(3):
            counts = np.bincount(img[:, :, c].ravel(), minlength=256)
            limit = 0.004 * n
            excess = np.maximum(counts - limit, 0).sum()
            clipped = np.minimum(counts, limit) + excess / 256
            cdf = np.cumsum(clipped)
            bound = 255 * (limit + excess / 256) / (n - cdf[cdf > 0][0]) + 1
            assert np.max(np.diff(lut[:, c])) <= bound


def test_apply_lut_matches_indexing():
    rng = np.random.default_rng(1)
    lut = rng.integers(0, 256, (256, 3), dtype=np.uint8)
    img = rng.integers(0, 256, (17, 23, 3), dtype=np.uint8)
    expected = np.stack([lut[img[:, :, c], c] for c in range(3)], axis=2)
    np.testing.assert_array_equal(apply_lut(img, lut), expected)
    # One table for every channel, and a grey image.
    np.testing.assert_array_equal(apply_lut(img, lut[:, 1]), lut[:, 1][img])
    grey = img[:, :, 0]
    np.testing.assert_array_equal(apply_lut(grey, lut[:, 0]), lut[grey, 0])


def test_one_lut_for_all_frames_keeps_mapping_consistent():
    """The point of MCIE: equal input levels give equal outputs in target and source frames."""
    rng = np.random.default_rng(2)
    target = rng.integers(0, 80, (30, 40, 3), dtype=np.uint8)
    source = np.roll(target, 3, axis=1)
    lut = mcie_lut(target)
    a, b = apply_lut(target, lut), apply_lut(source, lut)
    np.testing.assert_array_equal(np.roll(a, 3, axis=1), b)
    assert a.mean() > target.mean()  # a dark frame gets brighter


def test_constant_image_and_bad_input():
    flat = np.full((10, 10, 3), 77, np.uint8)
    lut = mcie_lut(flat)
    assert np.all(np.diff(lut.astype(int), axis=0) >= 0)
    np.testing.assert_array_equal(mcie_lut(flat, clip=1.0)[:, 0], np.arange(256))
    with pytest.raises(ParameterError, match="--reference: must be uint8"):
        mcie_lut(np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(ParameterError, match="--image: is empty"):
        apply_lut(np.zeros((0, 4), np.uint8), np.zeros(256, np.uint8))
    with pytest.raises(ParameterError, match=r"--lut: must have shape \(256, 3\)"):
        apply_lut(flat, np.zeros((256, 2), np.uint8))
    with pytest.raises(ParameterError):
        mcie_lut(flat, clip=0)
    with pytest.raises(ParameterError):
        mcie_lut(flat, bins=128)
    with pytest.raises(ParameterError):
        mcie_lut(np.zeros((0, 4, 3), np.uint8))
    with pytest.raises(ParameterError):
        apply_lut(flat, np.zeros((256, 2), np.uint8))
    with pytest.raises(ParameterError):
        apply_lut(flat, np.zeros(255, np.uint8))


# ----------------------------------------------------------------- RNW's integer arithmetic


def _rnw_reference_lut(channel: np.ndarray, clip: float) -> list[int]:
    """From issue 17's description of RNW's released code, in Python integers: clip limit
    truncated to an integer, round(excess / 256) whole pixels added to every bin, table
    values truncated to uint8."""
    n = channel.size
    counts = [0] * 256
    for v in channel.ravel().tolist():
        counts[v] += 1
    limit = int(clip * n)
    excess = sum(max(c - limit, 0) for c in counts)
    add = round(excess / 256)
    hist = [min(c, limit) + add for c in counts]
    cdf, acc = [], 0
    for h in hist:
        acc += h
        cdf.append(acc)
    nonzero = [c for c in cdf if c > 0]
    if not nonzero or nonzero[0] == cdf[-1]:
        return list(range(256))
    lo, hi = nonzero[0], cdf[-1]
    return [int(Fraction(max(c - lo, 0) * 255, hi - lo)) for c in cdf]


@pytest.mark.parametrize("clip", [0.004, 0.008, 0.05, 1.0])
def test_rnw_rounding_matches_its_description(clip):
    for img in _images():
        lut = mcie_lut(img, clip=clip, rounding="rnw")
        assert lut.shape == (256, 3) and lut.dtype == np.uint8
        for c in range(3):
            assert lut[:, c].tolist() == _rnw_reference_lut(img[:, :, c], clip)
        assert np.all(np.diff(lut.astype(int), axis=0) >= 0)
    # The default is unchanged by the option.
    np.testing.assert_array_equal(
        mcie_lut(_images()[0]), mcie_lut(_images()[0], rounding="nearest")
    )
    with pytest.raises(ParameterError, match="--rounding: must be one of nearest, rnw"):
        mcie_lut(_images()[0], rounding="floor")


def test_rnw_rounding_on_a_tiny_image_with_a_zero_clip_limit():
    # 10 pixels: int(0.004 * 10) = 0, every bin clipped to 0, round(10 / 256) = 0 added.
    img = np.arange(10, dtype=np.uint8).reshape(2, 5)
    np.testing.assert_array_equal(mcie_lut(img, rounding="rnw")[:, 0], np.arange(256))
    assert mcie_lut(img, rounding="rnw")[:, 0].tolist() == _rnw_reference_lut(img, 0.004)


def _real_rgb_images(real_dir):
    from sparsetools.io.image import read_image

    files = sorted((real_dir / "kitti-object-kuixu" / "image_2").glob("*.png"))
    files += sorted((real_dir / "kitti-depth-gt-metric3d" / "rgb").glob("*.png"))
    assert len(files) == 6
    return [read_image(f) for f in files]


@pytest.mark.real
def test_rnw_rounding_on_real_kitti_images(real_dir):
    """Bit-exact with the description on real frames; half the entries are one level lower."""
    differ, total = 0, 0
    for img in _real_rgb_images(real_dir):
        rnw = mcie_lut(img, rounding="rnw")
        for c in range(3):
            assert rnw[:, c].tolist() == _rnw_reference_lut(img[:, :, c], 0.004)
        d = mcie_lut(img).astype(int) - rnw.astype(int)
        assert set(np.unique(d)) <= {0, 1}  # truncation never gives a higher level
        differ += int(np.count_nonzero(d))
        total += d.size
    assert 0.4 < differ / total < 0.6
