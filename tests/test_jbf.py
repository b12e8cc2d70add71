"""Radar expansion (jbf_expand, height_extend) and its intrinsic error.

The reference below is written from METHODS.md section 3 alone: for every seed, every pixel of
its window gets C = exp(-|p-q|^2 / (2 sigma_s^2)) exp(-|I(p)-I(q)|^2 / (2 sigma_r^2)); all
candidates passing the threshold are collected and each pixel picks the best one globally
(no lookup tables, no pruning, no processing order).
"""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.intrinsic import intrinsic_error, mean_intrinsic_error
from sparsetools.ops.jbf import (
    _expand,
    _guidance_for,
    _half_windows,
    _seeds,
    height_extend,
    jbf_expand,
    pruning_radius,
)

KERNELS = ("jbf", "range", "spatial")
CONFLICTS = ("nearest", "max-confidence")
METRICS = ("gray", "rgb")


# -- independent reference ----------------------------------------------------------------------


def reference_expand(
    radar,
    guidance,
    *,
    fx,
    fy,
    sigma_s=25.0,
    sigma_r=10.0,
    threshold=0.05,
    window_m=(2.35, 2.35),
    kernel="jbf",
    range_metric="gray",
    conflict="nearest",
):
    H, W = radar.shape
    g = guidance
    if g.ndim == 3 and range_metric == "gray":
        g = cv2.cvtColor(g, cv2.COLOR_RGB2GRAY)
    g = g.astype(np.int64)
    if g.ndim == 2:
        g = g[:, :, None]
    seeds = [
        (y, x, np.float32(radar[y, x]))
        for y in range(H)
        for x in range(W)
        if np.isfinite(radar[y, x]) and radar[y, x] > 0
    ]
    is_seed = np.zeros((H, W), bool)
    for y, x, _ in seeds:
        is_seed[y, x] = True
    pix, dep, con = [], [], []
    for y0, x0, d in seeds:
        hu = int(np.floor(window_m[0] * fx / float(d) / 2))
        hv = int(np.floor(window_m[1] * fy / float(d) / 2))
        ys = np.arange(max(0, y0 - hv), min(H - 1, y0 + hv) + 1)
        xs = np.arange(max(0, x0 - hu), min(W - 1, x0 + hu) + 1)
        Y, X = np.meshgrid(ys, xs, indexing="ij")
        dist2 = (Y - y0) ** 2 + (X - x0) ** 2
        diff2 = ((g[Y, X, :] - g[y0, x0, :]) ** 2).sum(axis=-1)
        Gs = np.exp(-dist2 / (2 * sigma_s**2))
        Gr = np.exp(-diff2 / (2 * sigma_r**2))
        C = {"jbf": Gs * Gr, "range": Gr, "spatial": Gs}[kernel]
        keep = (C >= threshold) & ~is_seed[Y, X]
        pix.append((Y * W + X)[keep])
        con.append(C[keep].astype(np.float32))
        dep.append(np.full(keep.sum(), d, np.float32))
    depth = np.zeros(H * W, np.float32)
    conf = np.zeros(H * W, np.float32)
    if pix:
        pix, dep, con = (np.concatenate(a) for a in (pix, dep, con))
        # Best (depth, confidence) pair per pixel: nearest first, or most confident first.
        if conflict == "nearest":
            order = np.lexsort((-con, dep, pix))
        else:
            order = np.lexsort((dep, -con, pix))
        pix, dep, con = pix[order], dep[order], con[order]
        first = np.ones(pix.size, bool)
        first[1:] = pix[1:] != pix[:-1]
        depth[pix[first]] = dep[first]
        conf[pix[first]] = con[first]
    for y, x, d in seeds:
        depth[y * W + x] = d
        conf[y * W + x] = 1.0
    return depth.reshape(H, W), conf.reshape(H, W)


def random_scene(seed, *, H=26, W=34, n_seeds=14, rgb=True):
    """Small scene with few gray levels and few depths (many ties), seeds on all four borders."""
    rng = np.random.default_rng(seed)
    palette = np.array(
        [
            [0, 0, 0],
            [4, 3, 5],
            [9, 9, 9],
            [9, 9, 9],
            [30, 31, 29],
            [31, 30, 29],
            [120, 118, 121],
            [250, 250, 250],
        ],
        np.uint8,
    )
    guide = palette[rng.integers(0, len(palette), (H, W))]
    if not rgb:
        guide = guide[:, :, 0].copy()
    radar = np.zeros((H, W), np.float32)
    border = [
        (0, 0),
        (0, W - 1),
        (H - 1, 0),
        (H - 1, W - 1),
        (0, W // 2),
        (H // 2, 0),
        (H - 1, W // 3),
        (H // 3, W - 1),
    ]
    inner = [(int(rng.integers(0, H)), int(rng.integers(0, W))) for _ in range(n_seeds)]
    depths = np.array([1.0, 1.5, 1.5, 2.0, 3.0, 6.0], np.float32)
    for y, x in border + inner:
        radar[y, x] = depths[rng.integers(0, depths.size)]
    return radar, guide


# -- exactness against the reference ------------------------------------------------------------


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("conflict", CONFLICTS)
@pytest.mark.parametrize("metric", METRICS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_reference(kernel, conflict, metric, seed):
    radar, guide = random_scene(seed)
    # sigma_s 3: the pruning radius (8 px) cuts the windows; sigma_s 25: the windows do.
    for sigma_s, sigma_r, fx, fy in ((3.0, 10.0, 14.0, 10.0), (25.0, 30.0, 9.0, 12.0)):
        kw = dict(
            fx=fx,
            fy=fy,
            sigma_s=sigma_s,
            sigma_r=sigma_r,
            kernel=kernel,
            range_metric=metric,
            conflict=conflict,
        )
        depth, conf = jbf_expand(radar, guide, **kw)
        ref_depth, ref_conf = reference_expand(radar, guide, **kw)
        assert depth.dtype == np.float32 and conf.dtype == np.float32
        np.testing.assert_array_equal(depth, ref_depth)
        np.testing.assert_array_equal(conf, ref_conf)
        # The scene really exercises the windows: most pixels are reached, not all by one seed.
        assert np.count_nonzero(depth) > np.count_nonzero(radar) * 3


def test_windows_clipped_at_every_border_match_reference():
    # One near seed in each corner: its window (half size 11 x 8 px) sticks out on two sides.
    H, W = 20, 30
    rng = np.random.default_rng(5)
    guide = rng.integers(0, 3, (H, W), dtype=np.uint8) * 5
    radar = np.zeros((H, W), np.float32)
    for y, x in ((0, 0), (0, W - 1), (H - 1, 0), (H - 1, W - 1), (1, 15), (10, 1)):
        radar[y, x] = 1.0
    kw = dict(fx=10.0, fy=7.0, sigma_s=50.0, sigma_r=20.0)
    depth, conf = jbf_expand(radar, guide, **kw)
    ref_depth, ref_conf = reference_expand(radar, guide, **kw)
    np.testing.assert_array_equal(depth, ref_depth)
    np.testing.assert_array_equal(conf, ref_conf)
    # Half window floor(2.35 * 10 / 2) = 11 columns, floor(2.35 * 7 / 2) = 8 rows.
    assert depth[8, 11] > 0 and depth[0, 11] > 0
    alone = np.zeros((H, W), np.float32)
    alone[0, 0] = 1.0
    d1, _ = jbf_expand(alone, guide * 0, **kw)
    assert set(zip(*np.nonzero(d1), strict=True)) == {(y, x) for y in range(9) for x in range(12)}


def test_window_sizes_follow_depth_and_focal_lengths():
    # Uniform guidance, huge sigma: the expanded region is exactly the clipped window.
    H, W = 60, 80
    guide = np.full((H, W), 77, np.uint8)
    radar = np.zeros((H, W), np.float32)
    radar[30, 40] = 4.0
    depth, conf = jbf_expand(radar, guide, fx=20.0, fy=10.0, sigma_s=1e4, window_m=(2.0, 3.0))
    rows, cols = np.nonzero(depth)
    # u = 2 * 20 / 4 = 10 -> +-5 columns; v = 3 * 10 / 4 = 7.5 -> +-3 rows.
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (27, 33, 35, 45)
    assert np.all(depth[depth > 0] == np.float32(4.0))
    assert conf[30, 40] == 1.0 and np.all(conf[depth > 0] > 0.99)


# -- properties ---------------------------------------------------------------------------------


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("conflict", CONFLICTS)
@pytest.mark.parametrize("metric", METRICS)
def test_seed_order_does_not_matter(kernel, conflict, metric):
    radar, guide = random_scene(3, H=40, W=50, n_seeds=40)
    g = _guidance_for(guide, radar.shape, metric, kernel=kernel)
    rows, cols, depths = _seeds(radar)
    half_u, half_v = _half_windows(depths, 20.0, 16.0, 2.35, 2.35)
    kw = dict(sigma_s=8.0, sigma_r=40.0, threshold=0.05, kernel=kernel, conflict=conflict)
    base = _expand(rows, cols, depths, half_u, half_v, g, **kw)
    rng = np.random.default_rng(0)
    for order in (
        np.arange(rows.size)[::-1],
        rng.permutation(rows.size),
        rng.permutation(rows.size),
    ):
        out = _expand(rows, cols, depths, half_u, half_v, g, order=order, **kw)
        np.testing.assert_array_equal(out[0], base[0])
        np.testing.assert_array_equal(out[1], base[1])


@pytest.mark.parametrize("kernel", KERNELS)
@pytest.mark.parametrize("conflict", CONFLICTS)
def test_expanded_pixels_hold_seed_depths_and_seeds_keep_theirs(kernel, conflict):
    rng = np.random.default_rng(11)
    H, W = 90, 120
    guide = cv2.GaussianBlur(rng.integers(0, 256, (H, W, 3), dtype=np.uint8), (0, 0), 2)
    radar = np.zeros((H, W), np.float32)
    idx = rng.choice(H * W, 60, replace=False)
    radar.flat[idx] = rng.uniform(2, 30, idx.size).astype(np.float32)
    depth, conf = jbf_expand(radar, guide, fx=100.0, fy=100.0, kernel=kernel, conflict=conflict)
    seeds = radar > 0
    np.testing.assert_array_equal(depth[seeds], radar[seeds])
    assert np.all(conf[seeds] == 1.0)
    assert np.all(np.isin(depth[depth > 0], radar[seeds]))
    expanded = (depth > 0) & ~seeds
    assert expanded.sum() > 50 * seeds.sum()
    assert np.all(conf[expanded] >= np.float32(0.05)) and np.all(conf[expanded] <= 1.0)
    assert np.all(conf[depth == 0] == 0)
    if conflict == "nearest":
        # No pixel holds a depth farther than a seed that reaches it: compare with the
        # max-confidence map, whose pixels are reached by the same seeds.
        other, _ = jbf_expand(
            radar, guide, fx=100.0, fy=100.0, kernel=kernel, conflict="max-confidence"
        )
        np.testing.assert_array_equal(other > 0, depth > 0)
        assert np.all(depth[expanded] <= other[expanded])


def test_infinite_range_sigma_is_the_spatial_kernel():
    radar, guide = random_scene(7, H=50, W=60, n_seeds=30)
    for metric in METRICS:
        kw = dict(fx=20.0, fy=20.0, sigma_s=6.0, range_metric=metric)
        jbf = jbf_expand(radar, guide, sigma_r=1e12, kernel="jbf", **kw)
        spatial = jbf_expand(radar, guide, kernel="spatial", **kw)
        np.testing.assert_array_equal(jbf[0], spatial[0])
        np.testing.assert_array_equal(jbf[1], spatial[1])
        narrow = jbf_expand(radar, guide, sigma_r=2.0, kernel="jbf", **kw)
        assert np.count_nonzero(narrow[0]) < np.count_nonzero(spatial[0])


@pytest.mark.parametrize("kernel", KERNELS)
def test_raising_the_threshold_never_adds_pixels(kernel):
    radar, guide = random_scene(9, H=50, W=60, n_seeds=25)
    previous = None
    counts = []
    for thr in (0.01, 0.05, 0.2, 0.5, 0.9, 1.0):
        depth, _ = jbf_expand(
            radar, guide, fx=25.0, fy=25.0, sigma_s=8.0, sigma_r=60.0, threshold=thr, kernel=kernel
        )
        valid = depth > 0
        if previous is not None:
            assert not np.any(valid & ~previous)
        previous = valid
        counts.append(int(valid.sum()))
    assert counts[0] > counts[-2] >= counts[-1] >= np.count_nonzero(radar)


def test_pruning_radius_is_exact():
    for sigma_s, thr in ((25.0, 0.05), (3.0, 0.5), (10.0, 1.0), (7.3, 0.013)):
        r = pruning_radius(sigma_s, thr)
        assert math.exp(-((r + 1) ** 2) / (2 * sigma_s**2)) < thr
        assert r == math.ceil(sigma_s * math.sqrt(2 * math.log(1 / thr)))
    assert pruning_radius(25.0, 0.05) == 62


def test_empty_and_invalid_radar_give_empty_maps():
    guide = np.zeros((8, 9, 3), np.uint8)
    for radar in (np.zeros((8, 9), np.float32), np.full((8, 9), np.nan), np.full((8, 9), -3.0)):
        depth, conf = jbf_expand(radar, guide, fx=10, fy=10)
        assert depth.shape == (8, 9) and not depth.any() and not conf.any()
        assert depth.dtype == np.float32 and conf.dtype == np.float32
        assert not height_extend(radar, fy=10).any()


def test_nan_pixels_are_not_seeds_and_one_seed_works():
    radar = np.full((30, 30), np.nan, np.float32)
    radar[15, 15] = 5.0
    guide = np.full((30, 30), 100, np.uint8)
    depth, _ = jbf_expand(radar, guide, fx=20, fy=20, sigma_s=100)
    assert np.all(np.isfinite(depth)) and set(np.unique(depth)) == {0.0, 5.0}
    # floor(2.35 * 20 / 5 / 2) = 4 px each side.
    assert np.count_nonzero(depth) == 81


def test_gray_metric_uses_opencv_luminance():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (40, 40, 3), dtype=np.uint8)
    radar = np.zeros((40, 40), np.float32)
    radar[[5, 20, 33], [7, 20, 30]] = [3.0, 4.0, 2.5]
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    a = jbf_expand(radar, rgb, fx=30, fy=30, sigma_r=20)
    b = jbf_expand(radar, gray, fx=30, fy=30, sigma_r=20)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    c = jbf_expand(radar, rgb, fx=30, fy=30, sigma_r=20, range_metric="rgb")
    assert not np.array_equal(a[1], c[1])


def test_float64_radar_and_1_channel_guidance_are_accepted():
    radar, guide = random_scene(4, rgb=False)
    a = jbf_expand(radar.astype(np.float64), guide[:, :, None], fx=12, fy=12)
    b = jbf_expand(radar, guide, fx=12, fy=12)
    np.testing.assert_array_equal(a[0], b[0])


def test_kernel_is_cached_on_disk():
    from sparsetools.ops import jbf

    # cache=True: a new process loads the machine code instead of compiling again.
    for kernel in (jbf.expand, jbf.band, jbf._offset_table):
        assert type(kernel._cache).__name__ != "NullCache"


# -- bad input ----------------------------------------------------------------------------------


def _ok():
    radar = np.zeros((10, 12), np.float32)
    radar[5, 6] = 3.0
    return radar, np.zeros((10, 12, 3), np.uint8)


@pytest.mark.parametrize(
    "change, param, message",
    [
        (dict(guidance=np.zeros((10, 13, 3), np.uint8)), "guidance", "one shape"),
        (dict(radar_depth=np.zeros((11, 12), np.float32)), "guidance", "one shape"),
        (dict(fx=0.0), "fx", "> 0"),
        (dict(fy=-5.0), "fy", "> 0"),
        (dict(fx=float("nan")), "fx", "finite"),
        (dict(sigma_s=0.0), "sigma_s", "> 0"),
        (dict(sigma_r=-1.0), "sigma_r", "> 0"),
        (dict(threshold=0.0), "threshold", "(0, 1]"),
        (dict(threshold=1.5), "threshold", "(0, 1]"),
        (dict(threshold=-0.1), "threshold", "(0, 1]"),
        (dict(radar_depth=np.zeros((10, 12), np.uint8)), "radar_depth", "8-bit"),
        (dict(radar_depth=np.zeros((10, 12), np.uint16)), "radar_depth", "float metres"),
        (dict(radar_depth=np.zeros((10, 12), np.complex64)), "radar_depth", "floating point"),
        (dict(radar_depth=np.zeros((10, 12, 1), np.float32)), "radar_depth", "(H, W)"),
        (dict(guidance=np.zeros((10, 12), np.float32)), "guidance", "uint8"),
        (dict(guidance=np.zeros((10, 12, 4), np.uint8)), "guidance", "(H, W, 3)"),
        (dict(kernel="box"), "kernel", "one of"),
        (dict(conflict="farthest"), "conflict", "one of"),
        (dict(range_metric="lab"), "range_metric", "one of"),
        (dict(window_m=(0.0, 2.0)), "window_m", "> 0"),
        (dict(window_m=3.0), "window_m", "two numbers"),
        (dict(threads=0), "threads", ">= 1"),
    ],
)
def test_bad_input_raises_parameter_error(change, param, message):
    radar, guide = _ok()
    kw = dict(radar_depth=radar, guidance=guide, fx=10.0, fy=10.0)
    kw.update(change)
    with pytest.raises(ParameterError, match=re.escape(message)) as e:
        jbf_expand(kw.pop("radar_depth"), kw.pop("guidance"), **kw)
    # The parameter named as jbf_expand spells it; the command line shows it as an option.
    assert e.value.param == param
    assert str(e.value).startswith("--" + param.replace("_", "-") + ": ")


def test_height_extend_bad_input():
    radar, _ = _ok()
    with pytest.raises(ParameterError, match="fy"):
        height_extend(radar, fy=0)
    with pytest.raises(ParameterError, match="below-m"):
        height_extend(radar, fy=10, below_m=-1)
    with pytest.raises(ParameterError, match="8-bit"):
        height_extend(radar.astype(np.uint8), fy=10)


def test_pruning_radius_bad_input():
    with pytest.raises(ParameterError, match="sigma-s"):
        pruning_radius(0.0, 0.05)
    with pytest.raises(ParameterError, match="threshold"):
        pruning_radius(25.0, 0.0)


# -- height-extend ------------------------------------------------------------------------------


def reference_height_extend(radar, fy, below_m=0.25, above_m=1.5):
    H, W = radar.shape
    out = np.zeros((H, W), np.float32)
    for y in range(H):
        for x in range(W):
            d = radar[y, x]
            if not (np.isfinite(d) and d > 0):
                continue
            up = int(np.floor(above_m * fy / float(d)))
            down = int(np.floor(below_m * fy / float(d)))
            for yy in range(max(0, y - up), min(H - 1, y + down) + 1):
                if out[yy, x] == 0 or d < out[yy, x]:
                    out[yy, x] = d
    return out


def test_height_extend_matches_reference():
    rng = np.random.default_rng(1)
    H, W = 50, 20
    radar = np.zeros((H, W), np.float32)
    idx = rng.choice(H * W, 60, replace=False)
    radar.flat[idx] = rng.choice([2.0, 3.5, 5.0, 9.0], idx.size)
    radar[0, 0] = 1.0
    radar[H - 1, 3] = 1.0
    out = height_extend(radar, fy=40.0)
    np.testing.assert_array_equal(out, reference_height_extend(radar, 40.0))
    np.testing.assert_array_equal(
        height_extend(radar, fy=40.0, below_m=1.0, above_m=0.1),
        reference_height_extend(radar, 40.0, 1.0, 0.1),
    )


def test_height_extend_goes_up_more_than_down():
    radar = np.zeros((100, 5), np.float32)
    radar[50, 2] = 10.0
    out = height_extend(radar, fy=200.0)  # 1.5 m -> 30 px up, 0.25 m -> 5 px down
    rows = np.nonzero(out[:, 2])[0]
    assert (rows.min(), rows.max()) == (20, 55)
    assert np.count_nonzero(out) == 36


# -- intrinsic error ----------------------------------------------------------------------------


def test_intrinsic_error_by_hand():
    r = np.array([[10.0, 0, 20.0], [5.0, 30.0, 0]], np.float32)
    l = np.array([[12.0, 7.0, 20.0], [0, 100.0, 4.0]], np.float32)
    e = intrinsic_error(r, l)
    # Evaluated: (0,0) 10 vs 12 and (0,2) 20 vs 20; (1,1) has LiDAR above 80 m.
    assert e["evaluated"] == 2 and e["points"] == 4
    assert e["density_percent"] == pytest.approx(100 * 4 / 6)
    assert e["delta1"] == 1.0 and e["delta2"] == 1.0
    assert e["rmse"] == pytest.approx(math.sqrt(4 / 2))
    e = intrinsic_error(r, l, max_depth=200)
    assert e["evaluated"] == 3 and e["delta1"] == pytest.approx(2 / 3)
    assert e["delta2"] == pytest.approx(2 / 3)  # 100/30 = 3.33 > 1.5625
    assert list(e) == ["delta1", "delta2", "rmse", "points", "density_percent", "evaluated"]


def test_intrinsic_error_without_overlap_and_bad_shapes():
    e = intrinsic_error(np.zeros((3, 3)), np.ones((3, 3)))
    assert e["evaluated"] == 0 and e["points"] == 0 and math.isnan(e["rmse"])
    with pytest.raises(ParameterError, match="lidar"):
        intrinsic_error(np.zeros((3, 3)), np.zeros((3, 4)))
    m = mean_intrinsic_error([intrinsic_error(np.ones((2, 2)), np.ones((2, 2))), e])
    assert m["frames"] == 2 and m["rmse"] == 0.0 and m["points"] == 2.0


# -- accuracy: the ordering of the paper's Table 5 ----------------------------------------------

KITTI_FX = 721.5377  # P_rect_02 of 2011_09_26, the drive size of these 1242x375 frames


@pytest.mark.real
def test_kitti_radar_like_subsample_table5_ordering(real_dir):
    """60 noisy seeds drawn from KITTI semi-dense ground truth, expanded and compared to it."""
    from sparsetools.io.image import read_depth_png, read_image

    root = real_dir / "kitti-depth-gt-metric3d"
    for stem in ("0000000005", "0000000050", "0000000100"):
        gt = read_depth_png(root / "depth" / f"{stem}.png")
        rgb = read_image(root / "rgb" / f"{stem}.png")
        rng = np.random.default_rng(int(stem))
        # Radar sees a horizontal band around the horizon (rows 150-250 here).
        band = np.zeros(gt.shape, bool)
        band[150:250] = True
        ys, xs = np.nonzero((gt > 0) & band)
        pick = rng.choice(ys.size, 60, replace=False)
        radar = np.zeros_like(gt)
        noise = rng.normal(0, 0.2, pick.size).astype(np.float32)
        radar[ys[pick], xs[pick]] = gt[ys[pick], xs[pick]] + noise
        errors = {}
        for kernel in KERNELS:
            depth, _ = jbf_expand(radar, rgb, fx=KITTI_FX, fy=KITTI_FX, kernel=kernel)
            errors[kernel] = intrinsic_error(depth, gt)
        raw = intrinsic_error(radar, gt)
        assert raw["points"] == 60
        assert errors["jbf"]["points"] > 500 * raw["points"]
        assert errors["jbf"]["rmse"] < errors["range"]["rmse"]
        assert errors["jbf"]["rmse"] < errors["spatial"]["rmse"]
        assert errors["jbf"]["delta1"] > max(errors["range"]["delta1"], errors["spatial"]["delta1"])
        # A subset of either single-kernel expansion (C_jbf <= min(C_s, C_r)).
        assert errors["jbf"]["points"] < min(errors["range"]["points"], errors["spatial"]["points"])


@pytest.fixture(scope="module")
def synthetic_street(tmp_path_factory):
    from sparsetools.synth import generate_scene

    out = tmp_path_factory.mktemp("street")
    generate_scene(out, seed=0, frames=2, underwater_frames=0)
    return out


def test_synthetic_street_radar_table5_ordering(synthetic_street):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import read_depth_png, read_image
    from sparsetools.io.nuscenes import read_radar_pcd
    from sparsetools.ops.projection import project_points

    root = synthetic_street
    for stem in ("000000", "000001"):
        gt = read_depth_png(root / "depth_gt" / f"{stem}.png")
        rgb = read_image(root / "image_2" / f"{stem}.png")
        calib = load_calibration(root / "calib_radar" / f"{stem}.json")
        radar = project_points(read_radar_pcd(root / "radar" / f"{stem}.pcd"), calib)
        raw = intrinsic_error(radar, gt)
        assert raw["points"] > 50
        errors = {}
        for kernel in KERNELS:
            depth, _ = jbf_expand(radar, rgb, fx=calib.fx, fy=calib.fy, kernel=kernel)
            errors[kernel] = intrinsic_error(depth, gt)
        assert errors["jbf"]["points"] > 100 * raw["points"]
        assert errors["jbf"]["rmse"] < errors["range"]["rmse"]
        assert errors["jbf"]["rmse"] < errors["spatial"]["rmse"]
        # The expansion also beats the height-extend baseline (Table 1).
        ext = intrinsic_error(height_extend(radar, fy=calib.fy), gt)
        assert errors["jbf"]["rmse"] < ext["rmse"]
        assert errors["jbf"]["points"] > ext["points"]
