"""Underwater median compensation: medians, streaming, failure probability, recovery of albedo."""

from __future__ import annotations

import collections
import gc
import itertools
import math
import tracemalloc
import weakref
from pathlib import Path

import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.underwater import (
    UnderwaterCompensator,
    gray_world,
    median_failure_probability,
    window_median,
)

# ----------------------------------------------------------------- failure probability


def _p_fail_direct(n: int, c: float) -> float:
    # METHODS.md section 5, summed term by term.
    return sum(math.comb(n, u) * c**u * (1 - c) ** (n - u) for u in range(math.ceil(n / 2), n + 1))


@pytest.mark.parametrize("n", [1, 2, 3, 5, 10, 31, 101])
@pytest.mark.parametrize("c", [0.0, 0.05, 0.2, 0.4, 0.5, 0.7, 1.0])
def test_failure_probability_matches_direct_sum(n, c):
    assert median_failure_probability(n, c) == pytest.approx(_p_fail_direct(n, c), abs=1e-12)


def test_failure_probability_values_and_monotonicity():
    assert median_failure_probability(1, 0.3) == pytest.approx(0.3)
    assert median_failure_probability(31, 0.0) == 0.0
    assert median_failure_probability(31, 1.0) == pytest.approx(1.0)
    # For c < 0.5 a longer (odd) window fails less often; at 0.3 and n = 31 below 1 %.
    values = [median_failure_probability(n, 0.3) for n in (1, 3, 7, 15, 31, 61)]
    assert all(a > b for a, b in itertools.pairwise(values))
    assert values[4] < 0.01
    # For c > 0.5 it fails more often with more samples.
    assert median_failure_probability(31, 0.7) > median_failure_probability(3, 0.7)


@pytest.mark.parametrize("n, c", [(0, 0.2), (-3, 0.2), (2.5, 0.2), (5, -0.1), (5, 1.5)])
def test_failure_probability_bad_arguments(n, c):
    with pytest.raises(ParameterError):
        median_failure_probability(n, c)


# ----------------------------------------------------------------- window median


@pytest.mark.parametrize("dtype, high", [(np.uint8, 256), (np.uint16, 65536)])
@pytest.mark.parametrize("n", [1, 2, 7, 30, 31])
@pytest.mark.parametrize("pixels", [1, 4095, 4097, 10_000])
def test_window_median_matches_numpy(dtype, high, n, pixels):
    rng = np.random.default_rng(n * pixels)
    a = rng.integers(0, high, (n, pixels), dtype=dtype)
    expected = np.median(a, axis=0)
    np.testing.assert_array_equal(window_median(a), expected.astype(np.float32))
    np.testing.assert_array_equal(window_median(a, parallel=False), expected.astype(np.float32))


def test_window_median_extremes_and_float():
    a = np.zeros((5, 3, 4, 3), np.uint16)
    a[3:] = 65535  # two maxima among five: the median is still 0
    assert np.all(window_median(a) == 0)
    a[2:] = 65535
    assert np.all(window_median(a) == 65535)
    f = np.random.default_rng(1).normal(size=(6, 5, 7, 3)).astype(np.float32)
    np.testing.assert_allclose(window_median(f), np.median(f, axis=0), rtol=1e-6)
    with pytest.raises(ParameterError):
        window_median(np.full((3, 2, 2), np.nan, np.float32))
    with pytest.raises(ParameterError):
        window_median(np.zeros((0, 2, 2), np.uint8))


def test_gray_world_equalises_channel_means():
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1, (20, 30, 3)).astype(np.float32) * np.array([0.2, 1.0, 3.0], np.float32)
    out = gray_world(img)
    means = out.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(means, means.mean(), rtol=1e-5)
    # The overall mean is preserved.
    assert out.mean() == pytest.approx(img.mean(), rel=1e-5)


# ----------------------------------------------------------------- streaming vs reference


def _reference(seafloor, water, window, eps, a_ref=None):
    """Straightforward whole-sequence implementation of METHODS.md section 5 (float64)."""
    s = seafloor.astype(np.float64)
    B = np.median(water.astype(np.float64), axis=0)
    T, n, h = len(s), window, window // 2
    out, masks = [], []
    for t in range(T):
        start = min(max(t - h, 0), T - n)
        M = np.median(s[start : start + n], axis=0)
        if a_ref is None:
            M0 = np.median(s[:n], axis=0)
            a_ref = np.median((M0 - B).reshape(-1, s.shape[-1]), axis=0)
        F = (M - B) / a_ref
        masks.append(np.all(F >= eps, axis=2))
        out.append((s[t] - B) / np.maximum(F, eps))
    return np.stack(out), np.stack(masks), np.asarray(a_ref)


def _random_sequence(T=17, shape=(9, 11, 3), seed=0):
    rng = np.random.default_rng(seed)
    seafloor = rng.integers(30, 256, (T, *shape), dtype=np.uint8)
    water = rng.integers(0, 40, (4, *shape), dtype=np.uint8)
    return seafloor, water


@pytest.mark.parametrize("window", [1, 3, 5, 17])
def test_streaming_matches_reference(window):
    seafloor, water = _random_sequence()
    comp = UnderwaterCompensator(water, window=window, eps=0.05)
    got = list(comp.process(iter(seafloor)))
    ref, ref_mask, a_ref = _reference(seafloor, water, window, 0.05)
    assert len(got) == len(seafloor)
    np.testing.assert_allclose(comp.a_ref, a_ref, rtol=1e-6)
    np.testing.assert_allclose(np.stack([g[0] for g in got]), ref, rtol=1e-4, atol=1e-3)
    np.testing.assert_array_equal(np.stack([g[1] for g in got]), ref_mask)


def test_given_a_ref_and_float_frames():
    seafloor, water = _random_sequence(seed=3)
    comp = UnderwaterCompensator(water.astype(np.float32), window=5, a_ref=[50.0, 60.0, 70.0])
    got = np.stack([a for a, _ in comp.process(seafloor.astype(np.float32))])
    ref, _, _ = _reference(seafloor, water, 5, 1e-3, a_ref=np.array([50.0, 60.0, 70.0]))
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-3)
    # The scalar form applies to every channel.
    assert UnderwaterCompensator(water, window=5, a_ref=40).a_ref.tolist() == [40.0] * 3


def test_invalid_mask_where_factor_is_small():
    seafloor, water = _random_sequence(seed=4)
    seafloor[:, 2, 3] = 0  # the window median there is 0 < B: F < eps
    comp = UnderwaterCompensator(water, window=5)
    for _, valid in comp.process(seafloor):
        assert not valid[2, 3]
        assert valid.sum() >= valid.size - 5


def test_segments_give_the_single_pass_result():
    """Processing [lo, hi) with ``emit`` equals the full pass, as the CLI's segments rely on."""
    from sparsetools.pipeline.underwater import segment_tasks

    seafloor, water = _random_sequence(T=23, seed=5)
    full_comp = UnderwaterCompensator(water, window=7)
    full = [a for a, _ in full_comp.process(seafloor)]
    from sparsetools.io.sources import Frame, FrameKey

    frames = [Frame(FrameKey("", f"{i:03d}"), image=Path(f"{i:03d}.png")) for i in range(23)]
    tasks = segment_tasks(frames, Path("out"), window=7, a_ref=(1.0, 1.0, 1.0))
    import sparsetools.pipeline.underwater as uw

    seg = uw.segment_length(7)
    done = 0
    for k, t in enumerate(tasks):
        s = k * seg
        lo = s - t.inputs.emit[0]
        hi = lo + len(t.inputs.paths)
        comp = UnderwaterCompensator.from_backscatter(
            full_comp.backscatter, window=7, a_ref=full_comp.a_ref
        )
        out = [a for a, _ in comp.process(seafloor[lo:hi], emit=tuple(t.inputs.emit))]
        for j, a in enumerate(out):
            np.testing.assert_array_equal(a, full[s + j])
        done += len(out)
    assert done == len(seafloor)


def test_short_window_segments_at_both_ends():
    """emit at the very start and end of a sequence uses the shifted windows."""
    seafloor, water = _random_sequence(T=9, seed=6)
    comp = UnderwaterCompensator(water, window=5)
    full = [a for a, _ in comp.process(seafloor)]
    comp2 = UnderwaterCompensator.from_backscatter(comp.backscatter, window=5, a_ref=comp.a_ref)
    tail = [a for a, _ in comp2.process(seafloor, emit=(7, 9))]
    head = [a for a, _ in comp2.process(seafloor, emit=(0, 1))]
    np.testing.assert_array_equal(tail[0], full[7])
    np.testing.assert_array_equal(tail[1], full[8])
    np.testing.assert_array_equal(head[0], full[0])
    assert len(tail) == 2 and len(head) == 1


# ----------------------------------------------------------------- memory


def _generator(T, shape, recent=None):
    rng = np.random.default_rng(0)
    for _ in range(T):
        f = rng.integers(40, 256, shape, dtype=np.uint8)
        if recent is not None:
            recent.append(weakref.ref(f))
        yield f


def _peak_bytes(T, shape=(32, 40, 3), window=9):
    water = [np.full(shape, 10, np.uint8)] * 3
    comp = UnderwaterCompensator(water, window=window)
    gc.collect()
    tracemalloc.start()
    max_buffered = 0
    for _ in comp.process(_generator(T, shape)):
        max_buffered = max(max_buffered, comp.buffered)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak, max_buffered


def test_memory_does_not_grow_with_sequence_length():
    shape = (32, 40, 3)
    frame_bytes = int(np.prod(shape))
    short_peak, short_buf = _peak_bytes(30, shape)
    long_peak, long_buf = _peak_bytes(600, shape)
    assert short_buf == long_buf == 9  # the ring buffer holds exactly `window` frames
    # 600 frames would need 600 * frame_bytes = 2.3 MB if kept; the peak stays that of 30 frames.
    assert long_peak < short_peak + 4 * frame_bytes
    assert long_peak < 100 * frame_bytes


def test_caller_frames_are_released():
    """The compensator copies each frame into its ring buffer and keeps no reference."""
    shape = (16, 20, 3)
    water = [np.full(shape, 10, np.uint8)] * 3
    recent: collections.deque = collections.deque(maxlen=30)
    comp = UnderwaterCompensator(water, window=9)
    for _ in comp.process(_generator(200, shape, recent)):
        assert sum(r() is not None for r in recent) <= 1


def test_generator_is_consumed_lazily():
    seafloor, water = _random_sequence(T=50, seed=7)
    pulled = []

    def gen():
        for i, f in enumerate(seafloor):
            pulled.append(i)
            yield f

    it = UnderwaterCompensator(water, window=5).process(gen())
    next(it)
    assert len(pulled) == 5  # only the first window was read to emit frame 0
    for _ in range(10):
        next(it)
    assert len(pulled) == 5 + 8  # one more frame per output after the first h + 1


# ----------------------------------------------------------------- bad input


def test_bad_inputs():
    seafloor, water = _random_sequence(T=4)
    with pytest.raises(ParameterError, match="fewer than the median window"):
        list(UnderwaterCompensator(water, window=5).process(seafloor))
    with pytest.raises(ParameterError, match="no water-only frames"):
        UnderwaterCompensator([], window=3)
    with pytest.raises(ParameterError, match="--window: must be odd"):
        UnderwaterCompensator(water, window=4)
    with pytest.raises(ParameterError, match="--window: must be >= 1 and <= 65535"):
        UnderwaterCompensator(water, window=65537)
    with pytest.raises(ParameterError, match="--eps: must be a finite number > 0"):
        UnderwaterCompensator(water, window=3, eps=0)
    with pytest.raises(ParameterError, match=r"--water-frames\[1\]: must have shape"):
        UnderwaterCompensator([water[0], water[1][:5]], window=3)
    with pytest.raises(ParameterError, match="--backscatter: holds NaN"):
        UnderwaterCompensator.from_backscatter(np.full((4, 4, 3), np.nan), window=3)
    with pytest.raises(ParameterError):
        UnderwaterCompensator(water, window=3, a_ref=[1.0, -2.0, 3.0])
    with pytest.raises(ParameterError, match=r"--frames\[2\]: must have shape"):
        frames = [seafloor[0], seafloor[1], seafloor[2][:5]]
        list(UnderwaterCompensator(water, window=3).process(frames))
    mixed = [seafloor[0], seafloor[1], seafloor[2].astype(np.uint16)]
    with pytest.raises(ParameterError, match="frame 2 is uint16"):
        list(UnderwaterCompensator(water, window=3).process(mixed))
    nan_frames = [f.astype(np.float32) for f in seafloor]
    nan_frames[1][0, 0, 0] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        list(UnderwaterCompensator(water, window=3).process(nan_frames))
    bright_water = np.full_like(water, 255)
    with pytest.raises(ParameterError, match="not positive"):
        list(UnderwaterCompensator(bright_water, window=3).process(seafloor))


# ----------------------------------------------------------------- synthetic sequence


def _fit_rmse(est: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """Relative RMSE after the best per-channel scale (the global factor is unknown)."""
    err = 0.0
    for c in range(3):
        e, t = est[..., c][mask], truth[..., c][mask]
        s = float(e @ t) / float(e @ e)
        err += float(np.sum((s * e - t) ** 2))
    return math.sqrt(err / float(np.sum(truth[mask] ** 2)))


@pytest.fixture(scope="module")
def synthetic():
    from sparsetools.synth import generate_underwater

    return generate_underwater(seed=0, frames=60, water_frames=8, size=(160, 120))


def test_synthetic_sequence_recovers_albedo_and_removes_cone(synthetic):
    seq = synthetic
    comp = UnderwaterCompensator(seq.water, window=31)
    w = seq.seafloor.shape[2]
    before, after, corr_before, corr_after = [], [], [], []
    from sparsetools.synth import light_cone

    for t, (albedo, valid) in enumerate(comp.process(iter(seq.seafloor))):
        rec = seq.truth["seafloor"][t]
        col = rec["albedo_offset"][1]
        truth = seq.albedo[:, col : col + w].astype(np.float64) / 255.0
        cone = light_cone(*seq.seafloor.shape[1:3], **rec["cone"])
        mask = valid & (truth.min(axis=2) > 0.05)
        before.append(_fit_rmse(seq.seafloor[t].astype(np.float64), truth, mask))
        after.append(_fit_rmse(albedo.astype(np.float64), truth, mask))
        # Brightness relative to the true albedo: follows the cone before, not after.
        ratio_b = seq.seafloor[t].astype(np.float64).mean(axis=2) / truth.mean(axis=2)
        ratio_a = albedo.astype(np.float64).mean(axis=2) / truth.mean(axis=2)
        corr_before.append(np.corrcoef(ratio_b[mask], cone[mask])[0, 1])
        corr_after.append(np.corrcoef(ratio_a[mask], cone[mask])[0, 1])
    before, after = np.array(before), np.array(after)
    corr_before, corr_after = np.array(corr_before), np.array(corr_after)
    # Frames whose window is centred (the ends use a shifted window: the cone has moved).
    h = comp.window // 2
    mid = slice(h, len(before) - h)
    before_m, after_m = float(np.median(before[mid])), float(np.median(after[mid]))
    cb, ca = float(np.median(corr_before[mid])), float(np.median(corr_after[mid]))
    print(
        f"\nrelative RMSE vs albedo (median, centred windows): before {before_m:.3f} "
        f"after {after_m:.3f}; all frames: before {np.median(before):.3f} "
        f"after {np.median(after):.3f}"
    )
    print(f"correlation of brightness/albedo with the cone: before {cb:.3f} after {ca:.3f}")
    assert after_m < 0.5 * before_m
    assert after_m < 0.15
    assert np.median(after) < 0.6 * np.median(before)
    assert cb > 0.8
    # The generator's cone flickers (peak +-5 % per frame) and bobs: a median cannot remove
    # that part, so a small correlation remains.
    assert abs(ca) < 0.3 * cb
