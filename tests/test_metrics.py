"""depth_metrics against an independent pure-Python reference, and its conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.metrics import (
    METRIC_NAMES,
    aggregate_metrics,
    depth_metrics,
    format_metrics_table,
    garg_crop_mask,
)


def reference_metrics(pred, gt, min_depth=1e-3, max_depth=80.0, crop=None, median=False):
    """Pixel-by-pixel reference written from the definitions in METHODS.md section 6."""
    pairs = []
    h, w = gt.shape
    for y in range(h):
        for x in range(w):
            g = float(gt[y, x])
            if not (math.isfinite(g) and min_depth < g < max_depth):
                continue
            if crop is not None:
                top, bottom, left, right = crop
                if not (top <= y < bottom and left <= x < right):
                    continue
            pairs.append((float(pred[y, x]), g))
    if median:
        ps = sorted(p for p, _ in pairs)
        gs = sorted(g for _, g in pairs)

        def med(v):
            n = len(v)
            return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])

        s = med(gs) / med(ps)
        pairs = [(p * s, g) for p, g in pairs]
    pairs = [(min(max(p, min_depth), max_depth), g) for p, g in pairs]
    n = len(pairs)
    mean = lambda vals: sum(vals) / n  # noqa: E731
    d = [math.log(p) - math.log(g) for p, g in pairs]
    return {
        "abs_rel": mean([abs(g - p) / g for p, g in pairs]),
        "sq_rel": mean([(g - p) ** 2 / g for p, g in pairs]),
        "sq_rel_kitti": mean([((g - p) / g) ** 2 for p, g in pairs]),
        "rmse": math.sqrt(mean([(g - p) ** 2 for p, g in pairs])),
        "rmse_log": math.sqrt(mean([(math.log(g) - math.log(p)) ** 2 for p, g in pairs])),
        "log10": mean([abs(math.log10(g) - math.log10(p)) for p, g in pairs]),
        "silog": 100 * math.sqrt(max(mean([v * v for v in d]) - mean(d) ** 2, 0)),
        "delta1": mean([1.0 if max(g / p, p / g) < 1.25 else 0.0 for p, g in pairs]),
        "delta2": mean([1.0 if max(g / p, p / g) < 1.5625 else 0.0 for p, g in pairs]),
        "delta3": mean([1.0 if max(g / p, p / g) < 1.953125 else 0.0 for p, g in pairs]),
        "mae": mean([abs(g - p) for p, g in pairs]),
        "irmse": math.sqrt(mean([(1000 / g - 1000 / p) ** 2 for p, g in pairs])),
        "imae": mean([abs(1000 / g - 1000 / p) for p, g in pairs]),
        "n_pixels": n,
    }


def random_pair(seed, h=23, w=37):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0.5, 90.0, (h, w)).astype(np.float32)
    gt[rng.random((h, w)) < 0.3] = 0  # holes
    gt[0, 0] = np.nan
    pred = (gt * rng.uniform(0.6, 1.5, (h, w)) + rng.normal(0, 1, (h, w))).astype(np.float32)
    pred[rng.random((h, w)) < 0.05] = 0  # below min_depth: clipped
    pred[1, 1] = 200  # above max_depth: clipped
    return pred, gt


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference(seed):
    pred, gt = random_pair(seed)
    ours = depth_metrics(pred, gt)
    ref = reference_metrics(pred, gt)
    assert set(METRIC_NAMES) <= set(ours)
    assert ours["n_pixels"] == ref["n_pixels"]
    for k in METRIC_NAMES:
        assert ours[k] == pytest.approx(ref[k], rel=1e-9, abs=1e-12), k


def test_matches_reference_with_range_crop_and_median():
    pred, gt = random_pair(5, h=40, w=60)
    h, w = gt.shape
    crop = (int(0.40810811 * h), int(0.99189189 * h), int(0.03594771 * w), int(0.96405229 * w))
    ours = depth_metrics(
        pred, gt, min_depth=2.0, max_depth=50.0, garg_crop=True, median_scaling=True
    )
    ref = reference_metrics(pred, gt, min_depth=2.0, max_depth=50.0, crop=crop, median=True)
    assert ours["n_pixels"] == ref["n_pixels"] > 0
    for k in METRIC_NAMES:
        assert ours[k] == pytest.approx(ref[k], rel=1e-9, abs=1e-12), k
    assert ours["scale"] > 0


def test_hand_computed_values():
    # gt 10 and 20 m, prediction 12 and 15 m: every metric by hand.
    gt = np.array([[10.0, 20.0, 0.0]])
    pred = np.array([[12.0, 15.0, 33.0]])
    m = depth_metrics(pred, gt)
    assert m["n_pixels"] == 2
    assert m["abs_rel"] == pytest.approx((2 / 10 + 5 / 20) / 2)
    assert m["sq_rel"] == pytest.approx((4 / 10 + 25 / 20) / 2)
    assert m["sq_rel_kitti"] == pytest.approx((0.04 + 0.0625) / 2)
    assert m["rmse"] == pytest.approx(math.sqrt((4 + 25) / 2))
    assert m["mae"] == pytest.approx(3.5)
    # ratios 1.2 and 1.333: delta1 counts one, delta2 counts both
    assert (m["delta1"], m["delta2"], m["delta3"]) == (0.5, 1.0, 1.0)
    # BTS's log10: mean |log10 g - log10 p| = (log10(1.2) + log10(4/3)) / 2
    assert m["log10"] == pytest.approx((math.log10(1.2) + math.log10(4 / 3)) / 2)
    # inverse depth in 1/km: 100 - 83.33 and 50 - 66.67
    assert m["imae"] == pytest.approx((100 / 6 + 50 / 3) / 2)
    assert m["irmse"] == pytest.approx(math.sqrt(((100 / 6) ** 2 + (50 / 3) ** 2) / 2))


def test_perfect_prediction_and_scale_invariance_of_silog():
    _, gt = random_pair(3)
    gt = np.where(np.isfinite(gt) & (gt < 80), gt, 0)
    m = depth_metrics(gt, gt)
    for k in (
        "abs_rel",
        "sq_rel",
        "sq_rel_kitti",
        "rmse",
        "rmse_log",
        "log10",
        "silog",
        "mae",
        "irmse",
        "imae",
    ):
        assert m[k] == pytest.approx(0.0, abs=1e-9), k
    assert m["delta1"] == 1.0
    # a global scale changes rmse_log but not silog (scale invariant)
    scaled = depth_metrics(gt * 0.5, gt)
    assert scaled["silog"] == pytest.approx(0.0, abs=1e-6)
    assert scaled["rmse_log"] == pytest.approx(math.log(2), rel=1e-6)
    assert scaled["log10"] == pytest.approx(math.log10(2), rel=1e-6)
    # median scaling recovers the scale exactly
    ms = depth_metrics(gt * 0.5, gt, median_scaling=True)
    assert ms["scale"] == pytest.approx(2.0)
    assert ms["abs_rel"] == pytest.approx(0.0, abs=1e-9)


def test_prediction_clipped_to_range():
    gt = np.array([[5.0, 79.0]])
    m_zero = depth_metrics(np.array([[0.0, 79.0]]), gt)
    m_neg = depth_metrics(np.array([[-3.0, 79.0]]), gt)
    assert m_zero == m_neg  # both clipped to 1e-3
    assert m_zero["mae"] == pytest.approx((5 - 1e-3) / 2)
    m_far = depth_metrics(np.array([[5.0, 1e6]]), gt)
    m_inf = depth_metrics(np.array([[5.0, np.inf]]), gt)
    assert m_far == m_inf
    assert m_far["mae"] == pytest.approx(1 / 2)


def test_gt_range_is_exclusive():
    gt = np.array([[80.0, 1e-3, 40.0]])
    m = depth_metrics(np.full((1, 3), 40.0), gt)
    assert m["n_pixels"] == 1


def test_garg_crop_mask_bounds():
    mask = garg_crop_mask(375, 1242)
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    assert (rows[0], rows[-1] + 1, cols[0], cols[-1] + 1) == (153, 371, 44, 1197)


def test_no_valid_pixel_gives_nan_and_aggregate_skips_it():
    empty = depth_metrics(np.ones((4, 4)), np.zeros((4, 4)))
    assert empty["n_pixels"] == 0
    assert all(math.isnan(empty[k]) for k in METRIC_NAMES)
    pred_a, gt_a = random_pair(10)
    pred_b, gt_b = random_pair(11, h=5, w=9)
    a, b = depth_metrics(pred_a, gt_a), depth_metrics(pred_b, gt_b)
    agg = aggregate_metrics([a, empty, b])
    assert agg["n_images"] == 2 and agg["n_empty"] == 1
    assert agg["n_pixels"] == a["n_pixels"] + b["n_pixels"]
    for k in METRIC_NAMES:
        # per image then averaged: NOT pooled over pixels
        assert agg[k] == pytest.approx((a[k] + b[k]) / 2), k
    with pytest.raises(ParameterError, match="no valid ground-truth"):
        aggregate_metrics([empty])
    with pytest.raises(ParameterError):
        aggregate_metrics([])


def test_per_image_average_differs_from_pooled():
    gt1, p1 = np.full((1, 1), 10.0), np.full((1, 1), 11.0)
    gt2, p2 = np.full((1, 9), 10.0), np.full((1, 9), 10.0)
    agg = aggregate_metrics([depth_metrics(p1, gt1), depth_metrics(p2, gt2)])
    assert agg["rmse"] == pytest.approx(0.5)  # pooled would be sqrt(1/10)


def test_bad_input():
    with pytest.raises(ParameterError, match="--pred: is .* but gt is .*one shape"):
        depth_metrics(np.ones((3, 4)), np.ones((4, 3)))
    with pytest.raises(ParameterError, match=r"\(H, W\)"):
        depth_metrics(np.ones((1, 3, 4)), np.ones((1, 3, 4)))
    with pytest.raises(ParameterError, match="--max-depth.* must be > --min-depth"):
        depth_metrics(np.ones((3, 4)), np.ones((3, 4)), min_depth=10, max_depth=5)
    with pytest.raises(ParameterError, match="--min-depth: must be a finite number > 0"):
        depth_metrics(np.ones((3, 4)), np.ones((3, 4)), min_depth=0)
    with pytest.raises(ParameterError, match="--max-depth: must be a finite number > 0"):
        depth_metrics(np.ones((3, 4)), np.ones((3, 4)), max_depth=np.inf)
    with pytest.raises(ParameterError, match="--gt: must be floating point"):
        depth_metrics(np.ones((3, 4)), np.ones((3, 4), bool))
    pred = np.full((2, 2), 5.0)
    pred[0, 1] = np.nan
    with pytest.raises(ParameterError, match="NaN"):
        depth_metrics(pred, np.full((2, 2), 5.0))
    # NaN where gt is invalid does not matter
    gt = np.full((2, 2), 5.0)
    gt[0, 1] = 0
    assert depth_metrics(pred, gt)["n_pixels"] == 3


def test_inputs_unchanged_and_dtype_independent():
    pred, gt = random_pair(7)
    p0, g0 = pred.copy(), gt.copy()
    m32 = depth_metrics(pred, gt)
    np.testing.assert_array_equal(pred, p0)
    np.testing.assert_array_equal(gt, g0)
    m64 = depth_metrics(pred.astype(np.float64), gt.astype(np.float64))
    for k in METRIC_NAMES:
        assert m32[k] == pytest.approx(m64[k], rel=1e-12)


def test_table_lists_every_metric():
    pred, gt = random_pair(8)
    text = format_metrics_table(aggregate_metrics([depth_metrics(pred, gt)]), title="t")
    lines = text.splitlines()
    assert lines[0] == "t"
    for k in METRIC_NAMES:
        assert any(line.startswith(k + " ") for line in lines), k
