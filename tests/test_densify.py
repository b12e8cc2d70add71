"""IP-Basic and the nearest / linear baselines (sparsetools.ops.densify).

Every IP-Basic step is checked against a reference written here from METHODS.md section 10
and the published definitions of the OpenCV operations (grey dilation / erosion with the
border ignored, median with replicated border, Gaussian and bilateral with reflect-101
border), with numpy loops over kernel offsets on small maps. The stages come from
``ip_basic_stages``, so each stage is compared with the reference applied to the stage
before it.
"""

from __future__ import annotations

import numpy as np
import pytest

from sparsetools.errors import ParameterError
from sparsetools.ops.densify import (
    DensifyResult,
    DensifySettings,
    densify,
    fill_linear,
    fill_nearest,
    ip_basic,
    ip_basic_stages,
)

MAX_DEPTH = 100.0

# -- reference operations (written from the definitions) -----------------------------------------


def kernel_offsets(footprint):
    r = footprint.shape[0] // 2
    return [(dy - r, dx - r) for dy, dx in zip(*np.nonzero(footprint), strict=True)]


def shifted(a, dy, dx, pad):
    """a[y + dy, x + dx] with ``pad`` outside the map."""
    H, W = a.shape
    out = np.full_like(a, pad)
    ys, yd = slice(max(dy, 0), H + min(dy, 0)), slice(max(-dy, 0), H + min(-dy, 0))
    xs, xd = slice(max(dx, 0), W + min(dx, 0)), slice(max(-dx, 0), W + min(-dx, 0))
    out[yd, xd] = a[ys, xs]
    return out


def ref_dilate(a, footprint):
    return np.max([shifted(a, dy, dx, -np.inf) for dy, dx in kernel_offsets(footprint)], axis=0)


def ref_erode(a, footprint):
    return np.min([shifted(a, dy, dx, np.inf) for dy, dx in kernel_offsets(footprint)], axis=0)


def ref_close(a, footprint):
    return ref_erode(ref_dilate(a, footprint), footprint)


def ref_fill(a, footprint, where=None):
    empty = a < 0.1
    if where is not None:
        empty &= where
    return np.where(empty, ref_dilate(a, footprint), a)


def ref_median5(a):
    p = np.pad(a, 2, mode="edge")
    H, W = a.shape
    out = np.empty_like(a)
    for y in range(H):
        for x in range(W):
            out[y, x] = np.median(p[y : y + 5, x : x + 5])
    return out


def ref_gaussian5(a):
    k = np.array([1, 4, 6, 4, 1], np.float64) / 16  # OpenCV's 5-tap kernel for sigma 0
    p = np.pad(a.astype(np.float64), 2, mode="reflect")  # numpy "reflect" = OpenCV reflect-101
    H, W = a.shape
    rows = sum(k[i] * p[i : i + H, :] for i in range(5))
    return sum(k[j] * rows[:, j : j + W] for j in range(5))


def ref_bilateral(a, sigma_color, sigma_space, radius=2):
    p = np.pad(a.astype(np.float64), radius, mode="reflect")
    H, W = a.shape
    num = np.zeros((H, W))
    den = np.zeros((H, W))
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy * dy + dx * dx > radius * radius:
                continue
            q = p[radius + dy : radius + dy + H, radius + dx : radius + dx + W]
            w = np.exp(-(dy * dy + dx * dx) / (2 * sigma_space**2))
            w = w * np.exp(-((q - a) ** 2) / (2 * sigma_color**2))
            num += w * q
            den += w
    return num / den


def ref_extend_to_top(a):
    out = a.copy()
    for x in range(a.shape[1]):
        rows = np.nonzero(a[:, x] > 0.1)[0]
        if rows.size:
            out[: rows[0], x] = a[rows[0], x]
    return out


def ref_top_mask(a):
    mask = np.ones(a.shape, bool)
    for x in range(a.shape[1]):
        rows = np.nonzero(a[:, x] > 0.1)[0]
        mask[: rows[0] if rows.size else 0, x] = False
    return mask


FULL = {n: np.ones((n, n), np.uint8) for n in (5, 7, 9, 31)}
DIAMOND5 = np.array(
    [[0, 0, 1, 0, 0], [0, 1, 1, 1, 0], [1, 1, 1, 1, 1], [0, 1, 1, 1, 0], [0, 0, 1, 0, 0]], np.uint8
)


def cross(n):
    k = np.zeros((n, n), np.uint8)
    k[n // 2] = 1
    k[:, n // 2] = 1
    return k


def sparse_map(shape=(30, 44), density=0.06, seed=0, lo=2.0, hi=90.0, top=6):
    """Random sparse map with no points in the top ``top`` rows (like a LiDAR map)."""
    rng = np.random.default_rng(seed)
    d = np.where(rng.random(shape) < density, rng.uniform(lo, hi, shape), 0.0).astype(np.float32)
    d[:top] = 0
    return d


# -- every step against the reference ------------------------------------------------------------


def stage_map(stages):
    return {s.name: s.values for s in stages}


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("variant", ["gaussian", "bilateral"])
@pytest.mark.parametrize("extrapolate", [True, False])
def test_fast_steps_match_reference(seed, variant, extrapolate):
    d = sparse_map(seed=seed)
    stages = ip_basic_stages(d, variant=variant, extrapolate=extrapolate)
    names = [s.name for s in stages]
    expected = ["invert", "dilate", "close", "fill_7x7"]
    expected += ["extend_to_top", "fill_31x31"] if extrapolate else []
    expected += ["median", variant, "uninvert"]
    assert names == expected
    s = stage_map(stages)
    inv = np.where(d > 0.1, MAX_DEPTH - d, 0).astype(np.float32)
    np.testing.assert_array_equal(s["invert"], inv)
    np.testing.assert_array_equal(s["dilate"], ref_dilate(inv, DIAMOND5))
    np.testing.assert_array_equal(s["close"], ref_close(s["dilate"], FULL[5]))
    np.testing.assert_array_equal(s["fill_7x7"], ref_fill(s["close"], FULL[7]))
    before_median = s["fill_7x7"]
    if extrapolate:
        np.testing.assert_array_equal(s["extend_to_top"], ref_extend_to_top(s["fill_7x7"]))
        np.testing.assert_array_equal(s["fill_31x31"], ref_fill(s["extend_to_top"], FULL[31]))
        before_median = s["fill_31x31"]
    np.testing.assert_array_equal(s["median"], ref_median5(before_median))
    m = s["median"]
    if variant == "gaussian":
        want = np.where(m > 0.1, ref_gaussian5(m), m)
        np.testing.assert_allclose(s["gaussian"], want, rtol=0, atol=2e-5)
    else:
        # OpenCV interpolates the colour weight from a table: a few 1e-4 of a metre here.
        np.testing.assert_allclose(s["bilateral"], ref_bilateral(m, 1.5, 2.0), rtol=0, atol=2e-3)
    last = s[variant]
    want = np.where(last > 0.1, MAX_DEPTH - last, 0)
    np.testing.assert_allclose(s["uninvert"], want, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(
        s["uninvert"], ip_basic(d, variant=variant, extrapolate=extrapolate).depth
    )


@pytest.mark.parametrize("variant", ["gaussian", "bilateral"])
@pytest.mark.parametrize("extrapolate", [True, False])
def test_multiscale_steps_match_reference(variant, extrapolate):
    d = sparse_map(seed=3, density=0.05, lo=3.0, hi=60.0)
    stages = ip_basic_stages(d, variant=variant, extrapolate=extrapolate, multiscale=True)
    s = stage_map(stages)
    inv = np.where(d > 0.1, MAX_DEPTH - d, 0).astype(np.float32)
    np.testing.assert_array_equal(s["invert"], inv)
    merged = inv.copy()
    bins = [
        (d > 30.0, cross(3)),
        ((d > 15.0) & (d <= 30.0), cross(5)),
        ((d > 0.1) & (d <= 15), cross(7)),
    ]
    for mask, k in bins:
        dil = np.maximum(ref_dilate(np.where(mask, inv, 0), k), 0)
        merged = np.where(dil > 0.1, dil, merged)
    np.testing.assert_array_equal(s["multiscale_dilate"], merged)
    np.testing.assert_array_equal(s["close"], ref_close(merged, FULL[5]))
    c = s["close"]
    np.testing.assert_array_equal(s["median_valid"], np.where(c > 0.1, ref_median5(c), c))
    mv = s["median_valid"]
    np.testing.assert_array_equal(s["fill_9x9"], ref_fill(mv, FULL[9], ref_top_mask(mv)))
    f9 = s["fill_9x9"]
    if extrapolate:
        ext = ref_extend_to_top(f9)
        np.testing.assert_array_equal(s["extend_to_top"], ext)
        top = np.ones(d.shape, bool)
    else:
        ext = f9
        top = ref_top_mask(f9)
    large = ext
    for _ in range(6):
        large = ref_fill(large, FULL[5], top)
    np.testing.assert_array_equal(s["fill_5x5_x6"], large)
    valid = (large > 0.1) & top
    med = np.where(valid, ref_median5(large), large)
    np.testing.assert_array_equal(s["median"], med)
    if variant == "gaussian":
        want = np.where((med > 0.1) & top, ref_gaussian5(med), med)
        np.testing.assert_allclose(s["gaussian"], want, rtol=0, atol=2e-5)
    else:
        want = np.where(valid, ref_bilateral(med, 0.5, 2.0), med)
        np.testing.assert_allclose(s["bilateral"], want, rtol=0, atol=2e-3)


# -- known maps ----------------------------------------------------------------------------------


def test_constant_depth_on_rows_fills_exactly():
    d = np.zeros((40, 60), np.float32)
    d[12::5, ::2] = 17.25
    for kw in (
        {},
        {"variant": "bilateral"},
        {"multiscale": True},
        {"multiscale": True, "variant": "gaussian"},
    ):
        r = ip_basic(d, **kw)
        np.testing.assert_allclose(r.depth, 17.25, atol=1e-5)
    np.testing.assert_array_equal(fill_nearest(d).depth, 17.25)
    np.testing.assert_allclose(fill_linear(d).depth, 17.25, atol=1e-5)


def plane_on_rows(shape=(120, 200), step=4, first=20):
    """Depth of a real 3-D plane (inverse depth linear in u, v) and its samples on rows."""
    H, W = shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    inv = 1 / 20.0 + 1e-4 * (u - W / 2) + 2.5e-4 * (v - H / 2)  # 13..40 m
    truth = (1 / inv).astype(np.float32)
    sparse = np.zeros_like(truth)
    sparse[first::step] = truth[first::step]
    return truth, sparse


def test_plane_sampled_on_rows_fills_back_to_the_plane():
    from scipy import ndimage

    truth, sparse = plane_on_rows()
    rows = slice(20, 117)  # inside the sampled band
    # Every step takes a maximum, minimum, median or convex average of nearby values, and no
    # pixel is more than 2 rows from a sample, so the fill must stay inside the range the
    # plane spans over a 9x9 window; IP-Basic prefers the nearer sample, so it is biased near.
    lo = ndimage.minimum_filter(truth, 9)[rows] - 1e-4
    hi = ndimage.maximum_filter(truth, 9)[rows] + 1e-4
    for kw in ({}, {"variant": "bilateral"}, {"multiscale": True}):
        r = ip_basic(sparse, **kw).depth[rows]
        assert np.all((r >= lo) & (r <= hi)), kw
        rel = np.abs(r - truth[rows]) / truth[rows]
        assert rel.max() < 0.02 and np.median(rel) < 0.005, (kw, rel.max())
        assert np.mean(r - truth[rows]) < 0
    # Linear interpolation between rows: the plane's depth is not linear in (u, v), only its
    # inverse is, so the chord error over 4 rows stays far below 0.1 %.
    rel = np.abs(fill_linear(sparse).depth[rows] - truth[rows]) / truth[rows]
    assert rel.max() < 1e-3


def test_linear_is_exact_for_a_linear_map_inside_the_hull():
    rng = np.random.default_rng(5)
    H, W = 50, 70
    v, u = np.mgrid[0:H, 0:W]
    truth = (10 + 0.05 * u + 0.12 * v).astype(np.float64)
    sparse = np.zeros((H, W), np.float32)
    idx = rng.choice(H * W, 80, replace=False)
    sparse.flat[idx] = truth.flat[idx]
    sparse[[0, 0, H - 1, H - 1], [0, W - 1, 0, W - 1]] = truth[
        [0, 0, H - 1, H - 1], [0, W - 1, 0, W - 1]
    ]
    r = fill_linear(sparse)
    np.testing.assert_allclose(r.depth, truth, rtol=1e-5)
    assert r.measured.sum() == np.count_nonzero(sparse)


def test_linear_matches_brute_force_barycentric_on_the_delaunay_triangles():
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(12)
    H, W = 40, 60
    d = np.zeros((H, W), np.float32)
    idx = rng.choice(H * W, 80, replace=False)
    d.flat[idx] = rng.uniform(2, 80, 80)
    d[20, :] = np.where(rng.random(W) < 0.5, 30.0, 0)  # a ring-like row: collinear points
    v, u = np.nonzero(d > 0)
    P = np.column_stack([u, v]).astype(float)
    tri = Delaunay(P).simplices
    # For every pixel and every triangle, float barycentric coordinates (what
    # scipy.interpolate.LinearNDInterpolator evaluates on this triangulation).
    qv, qu = np.mgrid[0:H, 0:W]
    q = np.column_stack([qu.ravel(), qv.ravel()]).astype(float)
    A, B, C = P[tri[:, 0]], P[tri[:, 1]], P[tri[:, 2]]
    det = (B[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (C[:, 0] - A[:, 0]) * (B[:, 1] - A[:, 1])
    dx, dy = q[:, None, 0] - A[None, :, 0], q[:, None, 1] - A[None, :, 1]
    lb = (dx * (C[:, 1] - A[:, 1]) - dy * (C[:, 0] - A[:, 0])) / det
    lc = (dy * (B[:, 0] - A[:, 0]) - dx * (B[:, 1] - A[:, 1])) / det
    la = 1 - lb - lc
    inside = (la >= -1e-12) & (lb >= -1e-12) & (lc >= -1e-12)
    z = d[v, u].astype(float)
    val = la * z[tri[:, 0]] + lb * z[tri[:, 1]] + lc * z[tri[:, 2]]
    has = inside.any(axis=1)
    first = np.argmax(inside, axis=1)
    want = np.where(has, val[np.arange(q.shape[0]), first], 0.0).reshape(H, W)
    want = np.where(d > 0, d, want)
    got = fill_linear(d, outside="zero").depth
    np.testing.assert_array_equal(got > 0, want > 0)
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-5)


def test_linear_outside_the_hull():
    d = np.zeros((30, 40), np.float32)
    d[10, 10], d[10, 30], d[20, 20] = 5.0, 7.0, 9.0
    inside = fill_linear(d, outside="zero")
    # Point-in-triangle by barycentric coordinates, the reference for the hull.
    v, u = np.mgrid[0:30, 0:40]
    A, B, C = np.array([10, 10]), np.array([30, 10]), np.array([20, 20])
    det = (B[0] - A[0]) * (C[1] - A[1]) - (C[0] - A[0]) * (B[1] - A[1])
    l1 = ((B[0] - u) * (C[1] - v) - (C[0] - u) * (B[1] - v)) / det
    l2 = ((C[0] - u) * (A[1] - v) - (A[0] - u) * (C[1] - v)) / det
    l3 = 1 - l1 - l2
    tri = (l1 >= -1e-9) & (l2 >= -1e-9) & (l3 >= -1e-9)
    np.testing.assert_array_equal(inside.depth > 0, tri)
    np.testing.assert_allclose(inside.depth[tri], (5 * l1 + 7 * l2 + 9 * l3)[tri], rtol=1e-5)
    near = fill_linear(d, outside="nearest")
    np.testing.assert_array_equal(near.depth[~tri], fill_nearest(d).depth[~tri])
    assert np.all(near.depth > 0)


def test_linear_with_too_few_or_collinear_points_falls_back_to_outside():
    d = np.zeros((10, 12), np.float32)
    d[4, 2], d[4, 9] = 3.0, 6.0
    np.testing.assert_array_equal(fill_linear(d).depth, fill_nearest(d).depth)
    d[4, 5] = 4.0  # three collinear points: no triangle
    np.testing.assert_array_equal(fill_linear(d).depth, fill_nearest(d).depth)
    z = fill_linear(d, outside="zero")
    np.testing.assert_array_equal(z.depth, d)


def test_nearest_matches_brute_force():
    rng = np.random.default_rng(2)
    H, W = 23, 31
    d = np.zeros((H, W), np.float32)
    idx = rng.choice(H * W, 12, replace=False)
    d.flat[idx] = np.arange(1, 13, dtype=np.float32) * 1.5  # distinct depths
    r = fill_nearest(d)
    py, px = np.unravel_index(idx, (H, W))
    for y in range(H):
        for x in range(W):
            dist2 = (py - y) ** 2 + (px - x) ** 2
            candidates = d[py[dist2 == dist2.min()], px[dist2 == dist2.min()]]
            assert r.depth[y, x] in candidates
    np.testing.assert_array_equal(r.measured, d > 0)
    np.testing.assert_array_equal(r.depth[d > 0], d[d > 0])


# -- properties ----------------------------------------------------------------------------------

ALL_METHODS = [
    ("ip-basic", {}),
    ("ip-basic", {"variant": "bilateral", "extrapolate": False}),
    ("ip-basic", {"multiscale": True}),
    ("nearest", {}),
    ("linear", {}),
    ("linear", {"outside": "zero"}),
]


@pytest.mark.parametrize(("method", "kw"), ALL_METHODS)
def test_empty_map_gives_zeros(method, kw):
    r = densify(np.zeros((15, 20), np.float32), DensifySettings(method=method, **kw))
    assert isinstance(r, DensifyResult)
    assert r.depth.dtype == np.float32 and r.depth.shape == (15, 20)
    assert not r.depth.any() and not r.measured.any()


@pytest.mark.parametrize(("method", "kw"), ALL_METHODS)
def test_bad_input_is_refused(method, kw):
    s = DensifySettings(method=method, **kw)
    d = sparse_map()
    for bad in (np.where(d > 0, np.nan, 0), np.where(d > 0, np.inf, 0), -d):
        with pytest.raises(ParameterError):
            densify(bad.astype(np.float32), s)
    with pytest.raises(ParameterError, match="float"):
        densify((d * 256).astype(np.uint16), s)
    with pytest.raises(ParameterError):
        densify(d[None], s)


@pytest.mark.parametrize(("method", "kw"), ALL_METHODS)
def test_input_untouched_and_measurements_kept_by_baselines(method, kw):
    d = sparse_map(seed=7)
    before = d.copy()
    r = densify(d, DensifySettings(method=method, **kw))
    np.testing.assert_array_equal(d, before)
    np.testing.assert_array_equal(r.measured, d > 0)
    if method != "ip-basic":
        np.testing.assert_array_equal(r.depth[r.measured], d[r.measured])
    np.testing.assert_array_equal(r.filled, (r.depth > 0) & ~r.measured)


def test_float64_input_gives_the_float32_result():
    d = sparse_map(seed=4)
    np.testing.assert_array_equal(ip_basic(d.astype(np.float64)).depth, ip_basic(d).depth)


@pytest.mark.parametrize("kw", [{}, {"variant": "bilateral"}, {"multiscale": True}])
def test_ip_basic_commutes_with_a_left_right_flip(kw):
    d = sparse_map(seed=8)
    a = ip_basic(d, **kw).depth
    b = ip_basic(d[:, ::-1].copy(), **kw).depth[:, ::-1]
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-4)


def test_ip_basic_output_stays_in_the_input_range_when_fully_filled():
    d = sparse_map(seed=9, density=0.15, top=0)
    r = ip_basic(d)  # fast, extrapolated, Gaussian: every pixel gets a value
    assert np.all(r.depth > 0)
    lo, hi = d[d > 0].min(), d[d > 0].max()
    assert r.depth.min() >= lo - 1e-4 and r.depth.max() <= hi + 1e-4


def test_without_extrapolation_nothing_far_above_the_top_measurement():
    d = sparse_map(shape=(50, 44), seed=10, top=25)
    first = int(np.nonzero(d.any(axis=1))[0][0])
    for kw in ({"extrapolate": False}, {"extrapolate": False, "multiscale": True}):
        out = ip_basic(d, **kw).depth
        # The kernels before the top mask reach at most 2 + 2 + 3 (fast) or 3 + 2 + 4
        # (multi-scale) rows up; 15 rows above the first measured row nothing is filled.
        assert not out[: first - 15].any(), kw
        assert out[first:].any()
    assert ip_basic(d).depth[: first - 15].all()  # extrapolated: filled to row 0


def test_single_point_and_border_points():
    d = np.zeros((25, 25), np.float32)
    d[0, 0] = 8.0
    # The bilateral blur ignores empty neighbours (their colour weight is ~0), so one point
    # spreads unchanged; the Gaussian of the paper averages them in at the edge of the filled
    # region and pushes those pixels farther, as the published code does.
    r = ip_basic(d, variant="bilateral")
    assert set(np.unique(r.depth).round(4)) == {0.0, 8.0}
    assert ip_basic(d).depth[0, 0] == pytest.approx(8.0, abs=1e-5)
    d[24, 24] = 30.0
    for res in (ip_basic(d, multiscale=True), fill_nearest(d), fill_linear(d)):
        assert res.depth[24, 24] == pytest.approx(30.0, abs=1e-4)


def test_radar_like_very_sparse_input():
    d = np.zeros((90, 160), np.float32)
    rng = np.random.default_rng(11)
    d[rng.integers(40, 60, 25), rng.integers(0, 160, 25)] = rng.uniform(5, 60, 25)
    lo, hi = d[d > 0].min() - 1e-3, d[d > 0].max() + 1e-3
    for settings in (
        DensifySettings(variant="bilateral"),
        DensifySettings(multiscale=True, variant="bilateral"),
        DensifySettings(method="nearest"),
        DensifySettings(method="linear"),
    ):
        r = densify(d, settings)
        assert r.density > 0.3, settings
        valid = r.depth > 0
        assert lo <= r.depth[valid].min() and r.depth[valid].max() <= hi, settings
    # Gaussian: inside the filled region (5x5 neighbourhood filled) the range holds too.
    from scipy import ndimage

    g = ip_basic(d).depth
    interior = ndimage.binary_erosion(g > 0, np.ones((5, 5)))
    assert interior.sum() > 0.3 * d.size
    assert lo <= g[interior].min() and g[interior].max() <= hi


def test_depths_beyond_the_inversion_range_are_ignored():
    d = np.zeros((20, 20), np.float32)
    d[10, 10] = 150.0  # beyond max_depth: the published code would carry a negative value
    d[10, 12] = 0.05  # below the 0.1 m validity threshold
    assert not ip_basic(d).depth.any()
    assert ip_basic(d, max_depth=200.0).depth[10, 10] == pytest.approx(150.0, abs=1e-4)


def test_settings_are_validated():
    for bad in (
        {"method": "cubic"},
        {"variant": "box"},
        {"outside": "edge"},
        {"max_depth": 0.1},
        {"max_depth": float("nan")},
        {"extrapolate": "yes"},
    ):
        with pytest.raises(ParameterError):
            DensifySettings(**bad)
    with pytest.raises(ParameterError) as err:
        ip_basic(sparse_map(), variant="median")
    assert err.value.param == "variant"  # the command line names it --variant
    with pytest.raises(ParameterError) as err:
        DensifySettings(max_depth=-5)
    assert err.value.param == "inversion_offset"  # what the field is: IP-Basic's offset
    with pytest.raises(ParameterError):
        densify(sparse_map(), {"method": "nearest"})
