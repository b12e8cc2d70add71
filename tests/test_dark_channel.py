"""Dark channel, LDDCV and its mask against straightforward per-pixel loops."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.dark_channel import (
    dark_channel,
    dark_channel_features,
    image_intensity,
    lddcv,
    lddcv_mask,
)


def ref_dark_channel(img, n):
    """min over RGB of min over the n x n window, the window clipped to the image."""
    h, w, _ = img.shape
    half = n // 2
    out = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            win = img[max(y - half, 0) : y + half + 1, max(x - half, 0) : x + half + 1]
            out[y, x] = win.min()
    return out


def ref_variation(x):
    """max over the 3x3 neighbours q (inside the image) of |x(i) - x(q)|."""
    h, w = x.shape
    out = np.zeros((h, w))
    for y in range(h):
        for c in range(w):
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    q = (y + dy, c + dx)
                    if 0 <= q[0] < h and 0 <= q[1] < w:
                        out[y, c] = max(out[y, c], abs(x[y, c] - x[q]))
    return out


def images():
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (23, 31, 3), dtype=np.uint8)
    smooth = np.clip(np.linspace(0, 255, 40)[None, :, None] + rng.normal(0, 4, (18, 40, 3)), 0, 255)
    blocks = np.zeros((20, 20, 3), np.uint8)
    blocks[:, 10:] = (200, 150, 90)
    blocks[5:8, 2:5] = (30, 255, 255)
    return [noise, smooth.astype(np.uint8), blocks]


@pytest.mark.parametrize("window", [15, 3, 1, 7])
def test_dark_channel_equals_reference(window):
    for img in images():
        unit = img.astype(np.float64) / 255
        dc = dark_channel(img, window=window)
        assert dc.dtype == np.float32 and dc.shape == img.shape[:2]
        np.testing.assert_allclose(dc, ref_dark_channel(unit, window), rtol=0, atol=1e-7)
        # float input in [0, 1] gives the same
        np.testing.assert_allclose(dark_channel(unit, window=window), dc, atol=1e-7)


def test_lddcv_equals_reference_and_intensity_is_rgb_mean():
    for img in images():
        unit = img.astype(np.float64) / 255
        y = unit.mean(axis=2)
        var = lddcv(img)
        assert var.shape == (*img.shape[:2], 2) and var.dtype == np.float32
        np.testing.assert_allclose(image_intensity(img), y, atol=1e-6)
        np.testing.assert_allclose(var[..., 0], ref_variation(y), atol=1e-6)
        np.testing.assert_allclose(var[..., 1], ref_variation(ref_dark_channel(unit, 15)),
                                   atol=1e-6)  # fmt: skip
        luma = lddcv(img, intensity="luma")[..., 0]
        grey = unit @ np.array([0.299, 0.587, 0.114])
        np.testing.assert_allclose(luma, ref_variation(grey), atol=2e-5)


def test_mask_norm_any_separate():
    for img in images():
        unit = img.astype(np.float64) / 255
        a = ref_variation(unit.mean(axis=2))
        b = ref_variation(ref_dark_channel(unit, 15))
        feats = dark_channel_features(img)
        expected = np.vectorize(lambda u, v: math.hypot(u, v) > 0.05)(a, b)
        np.testing.assert_array_equal(feats.mask, expected)
        var = feats.lddcv
        np.testing.assert_array_equal(lddcv_mask(var, combine="any"), (a > 0.05) | (b > 0.05))
        sep = lddcv_mask(var, combine="separate", threshold=0.1)
        np.testing.assert_array_equal(sep, np.stack([a > 0.1, b > 0.1], axis=2))
        assert (feats.window, feats.threshold, feats.combine) == (15, 0.05, "norm")


def test_properties_constant_image_and_one_pixel():
    flat = np.full((12, 9, 3), 77, np.uint8)
    feats = dark_channel_features(flat)
    assert np.all(feats.dark == np.float32(77 / 255)) and not feats.lddcv.any()
    assert not feats.mask.any()
    one = np.array([[[10, 200, 30]]], np.uint8)
    f1 = dark_channel_features(one)
    assert f1.dark[0, 0] == np.float32(10 / 255) and f1.lddcv.shape == (1, 1, 2)
    assert not f1.mask.any()
    # A single bright dot: the dark channel ignores it (the other channels stay dark), the
    # intensity variation marks its 3x3 neighbourhood only.
    img = np.zeros((30, 30, 3), np.uint8)
    img[15, 15] = 255
    feats = dark_channel_features(img)
    assert feats.dark.max() == 0
    assert set(map(tuple, np.argwhere(feats.mask))) == {(15 + a, 15 + b) for a in (-1, 0, 1)
                                                        for b in (-1, 0, 1)}  # fmt: skip
    # Blurring lowers the variation (the paper's cue).
    import cv2

    sharp = images()[0]
    blurred = cv2.GaussianBlur(sharp, (0, 0), 3)
    assert lddcv(blurred).mean() < 0.3 * lddcv(sharp).mean()


def test_bad_input():
    img = images()[0]
    with pytest.raises(ParameterError, match="odd"):
        dark_channel(img, window=4)
    with pytest.raises(ParameterError, match=r"--image: must have shape \(H, W, 3\)"):
        dark_channel(img[:, :, 0])
    with pytest.raises(ParameterError, match="--image: must be uint8 or float32 or float64"):
        dark_channel(img.astype(np.uint16))
    with pytest.raises(ParameterError, match="--image: must be a numpy array"):
        dark_channel(img.tolist())
    with pytest.raises(ParameterError, match="--dark: is .* but image is"):
        lddcv(img, dark=np.zeros((3, 3), np.float32))
    with pytest.raises(ParameterError, match=r"--variation: must have shape \(H, W, 2\)"):
        lddcv_mask(np.zeros((3, 3)))
    with pytest.raises(ParameterError, match="--threshold: must be a finite number >= 0"):
        lddcv_mask(lddcv(img), threshold=-1)
    with pytest.raises(ParameterError, match=r"\[0, 1\]"):
        dark_channel(img.astype(np.float32))
    nan = img.astype(np.float32) / 255
    nan[0, 0, 0] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        dark_channel(nan)
    with pytest.raises(ParameterError, match="intensity"):
        lddcv(img, intensity="hsv")
    with pytest.raises(ParameterError, match="combine"):
        lddcv_mask(lddcv(img), combine="mean")
    with pytest.raises(ParameterError, match="empty"):
        dark_channel(np.zeros((0, 4, 3), np.uint8))


def test_a_window_larger_than_the_image_is_bounded_by_it(monkeypatch):
    """A window of 2 max(H, W) - 1 covers the image from every pixel: any larger one gives the
    same map, and no kernel larger than that is built (30001 x 30001 bytes would be 900 MB)."""
    import cv2

    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (32, 64, 3), dtype=np.uint8)
    whole = dark_channel(image, window=127)
    assert np.all(whole == whole.min())  # the whole image's minimum everywhere
    sizes = []
    make = cv2.getStructuringElement
    monkeypatch.setattr(cv2, "getStructuringElement",
                        lambda shape, size: sizes.append(size) or make(shape, size))  # fmt: skip
    np.testing.assert_array_equal(dark_channel(image, window=30001), whole)
    assert sizes and max(max(s) for s in sizes) <= 127
