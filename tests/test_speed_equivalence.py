"""Speed changes of issue 18 change no output: each fast path against the way it was computed
before (the old code, written out here), on real frames, synthetic scans and adversarial input.

The pipeline side (file identities, thread limits, command outputs against stored digests) is
tests/test_speed_pipeline.py.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from sparsetools.calibration import Calibration
from sparsetools.errors import FormatError
from sparsetools.io.image import encode_depth_png
from sparsetools.io.kitti import drop_non_finite, read_velodyne_bin
from sparsetools.ops import jbf, projection
from sparsetools.ops._projection_kernels import zbuffer_depth
from sparsetools.ops.beams import horizon_rings, select_beams
from sparsetools.ops.lidar_profile import grouped_median
from sparsetools.ops.rings import _angle_from, recover_rings, ring_elevations, scan_order_rings
from test_beams import cone_scan

K_KITTI = np.array([[721.5377, 0, 609.5593], [0, 721.5377, 172.854], [0, 0, 1.0]])
T_KITTI = np.array([[7.533745e-03, -9.999714e-01, -6.166020e-04, -4.069766e-03],
                    [1.480249e-02, 7.280733e-04, -9.998902e-01, -7.631618e-02],
                    [9.998621e-01, 7.523790e-03, 1.480755e-02, -2.717806e-01],
                    [0, 0, 0, 1]])  # fmt: skip


def kitti_calib(width=1242, height=375):
    return Calibration(K=K_KITTI, T_cam_from_sensor=T_KITTI, width=width, height=height)


@pytest.fixture(scope="module")
def kitti_clouds(real_dir):
    velo = real_dir / "kitti-object-kuixu" / "velodyne"
    return [read_velodyne_bin(p) for p in sorted(velo.glob("*.bin"))]


# -- projection: the numpy pass against the compiled loop --------------------------------------


def both_zbuffers(points, calib, min_depth=0.1, max_depth=np.inf, offset=0):
    """(compiled map, its count), (numpy map, its count)."""
    M = np.ascontiguousarray(calib.projection, dtype=np.float64)
    width, height = calib.size
    a = np.zeros((height, width), np.float32)
    b = np.zeros((height, width), np.float32)
    n_a = zbuffer_depth(np.ascontiguousarray(points), M, min_depth, max_depth, offset, a)
    with np.errstate(all="ignore"):
        n_b = projection._zbuffer_depth_numpy(points, M, min_depth, max_depth, offset, b)
    return (a, int(n_a)), (b, n_b)


def assert_same_zbuffer(points, calib, **kw):
    (a, n_a), (b, n_b) = both_zbuffers(points, calib, **kw)
    assert n_a == n_b
    assert a.tobytes() == b.tobytes()  # bit for bit, Inf and -0 included
    return n_a


def border_cloud(rng, calib, n, min_depth, max_depth):
    """Points that project onto pixel borders (half-integers, the image edges) at depths on the
    depth limits: where a rounding difference would show."""
    M = calib.projection
    width, height = calib.size
    u = rng.choice([-0.5, 0.5, width - 0.5, width - 1.5, width + 0.5, 600.5], n)
    u = np.where(rng.random(n) < 0.5, u + rng.normal(0, 1e-9, n), rng.uniform(-20, width + 20, n))
    v = rng.choice([-0.5, 0.5, height - 0.5, height - 1.5, 100.5], n)
    v = np.where(rng.random(n) < 0.5, v, rng.uniform(-20, height + 20, n))
    limits = [min_depth, max_depth if math.isfinite(max_depth) else 90.0]
    w = np.where(rng.random(n) < 0.3, rng.choice(limits, n) * (1 + rng.normal(0, 1e-12, n)),
                 rng.uniform(-5, 100, n))  # fmt: skip
    X = np.linalg.solve(M[:, :3], np.stack([u * w, v * w, w]) - M[:, 3:4]).T
    return np.column_stack([X, rng.random(n)])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize(
    "min_depth, max_depth, offset", [(0.1, np.inf, 0), (0.0, 80.0, -1), (5.0, 5.0001, 0)]
)
def test_numpy_pass_equals_compiled_loop_on_pixel_and_depth_borders(
    dtype, min_depth, max_depth, offset
):
    rng = np.random.default_rng(int(min_depth * 10) - offset + 7 * (dtype is np.float32))
    calib = kitti_calib()
    landed = 0
    for _ in range(4):
        pts = border_cloud(rng, calib, 20000, min_depth, max_depth).astype(dtype)
        landed += assert_same_zbuffer(
            pts, calib, min_depth=min_depth, max_depth=max_depth, offset=offset
        )
    assert landed > 1000  # the borders were really exercised


def test_numpy_pass_equals_compiled_loop_on_broken_clouds():
    """NaN, Inf, huge values (float32 overflow: no pre-selection), duplicates, tiny clouds."""
    rng = np.random.default_rng(3)
    calib = kitti_calib(64, 32)
    for k in range(60):
        n = int(rng.integers(0, 9000))
        scale = rng.choice([1.0, 10.0, 1e20, 1e39 if k % 2 else 1.0], size=(n, 1))
        with np.errstate(over="ignore"):
            pts = (rng.normal(0, 1, (n, 4)) * scale).astype(np.float32 if k % 3 else np.float64)
        if n:
            with np.errstate(over="ignore"):
                pts[:, 0] = np.abs(pts[:, 0]) * 3
            pts[rng.integers(0, n, 5)] = np.nan
            pts[rng.integers(0, n, 5), rng.integers(0, 3, 5)] = np.inf
            pts[rng.integers(0, n, n // 3)] = pts[0]
        assert_same_zbuffer(pts, calib, min_depth=0.0 if k % 4 == 0 else 0.1, offset=-(k % 2))


def test_an_inf_depth_alone_in_a_pixel_stays_inf_as_in_the_compiled_loop():
    calib = Calibration(K=np.eye(3), T_cam_from_sensor=np.eye(4), width=4, height=3)
    pts = np.array([[0.0, 0.0, 1e300], [1.0, 1.0, 1.0]])  # w = 1e300 -> float32 Inf
    (a, _), (b, _) = both_zbuffers(pts, calib)
    assert np.isinf(a[0, 0]) and a.tobytes() == b.tobytes()


@pytest.mark.real
def test_numpy_pass_equals_compiled_loop_on_real_kitti(kitti_clouds, real_dir):
    from sparsetools.io.calib import load_calibration

    calibs = sorted((real_dir / "kitti-object-kuixu" / "calib").glob("*.txt"))
    for pts, path in zip(kitti_clouds, calibs, strict=True):
        calib = load_calibration(path, image_size=(1242, 375))
        for kw in ({}, {"offset": -1, "min_depth": 0.0}, {"max_depth": 20.0, "min_depth": 5.0}):
            assert assert_same_zbuffer(pts, calib, **kw) > 10000
        # the pre-selection keeps few more points than land (it is worth its cost)
        M = np.ascontiguousarray(calib.projection)
        rows = projection._candidates(pts, M, 0.1, np.inf, 0, (375, 1242))
        assert rows.size < 1.01 * assert_same_zbuffer(pts, calib) + 100


def test_project_points_gives_the_same_map_with_every_backend():
    rng = np.random.default_rng(5)
    calib = kitti_calib()
    pts = border_cloud(rng, calib, 30000, 0.1, np.inf).astype(np.float32)
    for kw in ({}, {"pixel_offset": -1, "min_depth": 0.0}, {"max_depth": 20.0}):
        maps = [
            projection.project_points(pts, calib, return_count=True, backend=b, **kw)
            for b in projection.BACKENDS
        ]
        assert maps[0][1] > 1000
        for depth, n_in in maps[1:]:
            assert n_in == maps[0][1] and depth.tobytes() == maps[0][0].tobytes()


def test_an_unknown_backend_is_refused():
    from sparsetools.errors import ParameterError

    with pytest.raises(ParameterError, match="backend"):
        projection.project_points(np.zeros((1, 3)), kitti_calib(), backend="cuda")


def test_auto_uses_the_compiled_kernel_once_numba_is_loaded(monkeypatch):
    import sys

    monkeypatch.setattr(projection, "_points_projected", 0)
    monkeypatch.setattr(projection, "COMPILED_AFTER_POINTS", 1000)
    monkeypatch.setitem(sys.modules, "numba", sys.modules.get("numba", object()))
    assert projection._use_compiled(10)  # loaded already: no points need to pay for it
    assert not projection._use_compiled(10**9, "numpy")
    assert projection._use_compiled(1, "compiled")


def test_the_switch_happens_after_enough_points_when_numba_is_not_loaded(monkeypatch):
    import sys

    monkeypatch.delitem(sys.modules, "numba", raising=False)
    monkeypatch.setattr(projection, "_points_projected", 0)
    monkeypatch.setattr(projection, "COMPILED_AFTER_POINTS", 1000)
    assert not projection._use_compiled(600)
    assert projection._use_compiled(600)  # 1200 > 1000 projected


def test_a_fresh_process_projects_without_loading_numba_and_auto_switches_when_it_is(tmp_path):
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from sparsetools.calibration import Calibration\n"
        "from sparsetools.ops.projection import project_points\n"
        "K = np.array([[100.0, 0, 8], [0, 100.0, 6], [0, 0, 1]])\n"
        "c = Calibration(K=K, T_cam_from_sensor=np.eye(4), width=16, height=12)\n"
        "pts = np.array([[0.0, 0.0, 5.0], [0.1, 0.0, 4.0]])\n"
        "a = project_points(pts, c)\n"
        "print('numba' in sys.modules)\n"
        "import numba  # noqa: F401\n"
        "b = project_points(pts, c)\n"
        "print('sparsetools.ops._projection_kernels' in sys.modules, a.tobytes() == b.tobytes())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True", "True"]


# -- reading clouds, encoding depth PNGs --------------------------------------------------------


def old_read_velodyne_bin(path, n_columns=4):
    raw = path.read_bytes()
    points = np.frombuffer(raw, dtype="<f4").reshape(-1, n_columns).astype(np.float32)
    finite = np.isfinite(points).all(axis=1)
    return points[finite] if not finite.all() else points


def test_read_velodyne_bin_gives_what_the_old_reader_gave(tmp_path):
    rng = np.random.default_rng(0)
    cases = {
        "plain": rng.normal(0, 30, (5000, 4)),
        "nan rows": np.where(rng.random((5000, 4)) < 0.01, np.nan, rng.normal(0, 30, (5000, 4))),
        "inf": np.where(rng.random((3000, 4)) < 0.01, -np.inf, 1.0),
        "huge (the sum overflows)": np.full((100, 4), 3e38),
        "empty": np.zeros((0, 4)),
        "one point": np.ones((1, 4)),
    }
    for name, pts in cases.items():
        path = tmp_path / f"{name}.bin"
        pts.astype("<f4").tofile(path)
        new = read_velodyne_bin(path)
        old = old_read_velodyne_bin(path)
        assert new.dtype == np.float32 and new.flags.writeable and new.flags.c_contiguous, name
        assert new.shape == old.shape and new.tobytes() == old.tobytes(), name
    five = tmp_path / "five.bin"
    rng.normal(size=(10, 5)).astype("<f4").tofile(five)
    assert (
        read_velodyne_bin(five, n_columns=5).tobytes() == old_read_velodyne_bin(five, 5).tobytes()
    )


def test_read_velodyne_bin_still_refuses_truncated_and_missing_files(tmp_path):
    bad = tmp_path / "cut.bin"
    bad.write_bytes(b"\0" * 18)
    with pytest.raises(FormatError, match="not a multiple of 16"):
        read_velodyne_bin(bad)
    with pytest.raises(FormatError, match="no such file"):
        read_velodyne_bin(tmp_path / "nope.bin")
    with pytest.raises(FormatError, match="is a folder"):
        read_velodyne_bin(tmp_path)


def test_drop_non_finite_returns_the_input_itself_when_all_is_finite():
    pts = np.ones((10, 4), np.float32)
    kept, dropped = drop_non_finite(pts)
    assert kept is pts and dropped == 0
    pts[3, 2] = np.nan
    kept, dropped = drop_non_finite(pts)
    assert dropped == 1 and kept.shape == (9, 4)


def old_encode_depth_png(depth):
    import cv2

    valid = np.isfinite(depth) & (depth > 0)
    scaled = np.rint(depth[valid].astype(np.float64) * 256.0)
    clipped = int(np.count_nonzero((scaled < 1) | (scaled > 65535)))
    out = np.zeros(depth.shape, dtype=np.uint16)
    out[valid] = np.clip(scaled, 1, 65535).astype(np.uint16)
    return cv2.imencode(".png", out)[1].tobytes(), clipped


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_encode_depth_png_gives_the_old_bytes(dtype):
    rng = np.random.default_rng(1)
    depth = rng.uniform(0, 300, (37, 53))
    depth[rng.random(depth.shape) < 0.6] = 0
    depth.flat[rng.integers(0, depth.size, 20)] = rng.choice(
        [np.nan, np.inf, -np.inf, -3.0, 1e-4, 1e30], 20
    )
    depth = depth.astype(dtype)
    for d in (depth, np.asfortranarray(depth), depth[::2, 1::3], np.zeros((5, 4), dtype)):
        assert encode_depth_png(d) == old_encode_depth_png(d)


# -- rings and beam selection -------------------------------------------------------------------


def old_scan_order_rings(points, n_lasers=None):
    n = points.shape[0]
    if n == 0:
        return np.zeros(0, np.int32)
    xy = points[:, :2].astype(np.float32)
    az = np.degrees(np.arctan2(xy[:, 1], xy[:, 0]))
    step = np.diff(az)
    step = np.where(step > 180, step - 360, np.where(step < -180, step + 360, step))
    if np.count_nonzero(step < 0) > step.size // 2:
        az = -az
    first = None
    for cut in (0.0, 180.0):
        a = (az - cut) % 360.0
        ring = np.zeros(n, np.int32)
        np.cumsum(np.diff(a) < -90.0, out=ring[1:])
        if n_lasers is None or int(ring[-1]) + 1 == n_lasers:
            return ring
        if first is None:
            first = ring
    return first


def old_grouped_median(values, label, k):
    order = np.argsort(label.astype(np.int16), kind="stable")
    grouped = values[order]
    count = np.bincount(label, minlength=k)
    bounds = np.concatenate([[0], np.cumsum(count)])
    med = np.full(k, np.nan)
    for g in np.flatnonzero(count):
        med[g] = np.median(grouped[bounds[g] : bounds[g + 1]])
    return med, count


def old_ring_elevations(points, ring, n_lasers=64, far_range=20.0, min_far_points=10):
    ring = ring.astype(np.intp)
    xyz = points[:, :3].astype(np.float64)
    r, z = np.hypot(xyz[:, 0], xyz[:, 1]), xyz[:, 2]
    el = np.degrees(np.arctan2(z, r))
    far = r > far_range
    far_med, far_count = old_grouped_median(el[far], ring[far], n_lasers)
    few = far_count < min_far_points
    if few.any():
        near = few[ring]
        all_med, _ = old_grouped_median(el[near], ring[near], n_lasers)
        far_med = np.where(few, all_med, far_med)
    return far_med


def test_angle_from_the_cut_equals_numpy_remainder():
    a = np.concatenate([
        (np.arange(-3_600_000, 1_800_001) / 10_000.0).astype(np.float32),
        np.array([-180.00002, 180.00002, -0.0, 0.0, -360.0, -1e-7, -1e-30, 179.99998], np.float32),
    ])  # fmt: skip
    for cut in (0.0, 180.0):
        assert np.array_equal(_angle_from(a, cut), (a - cut) % 360.0)


def synthetic_clouds():
    rng = np.random.default_rng(0)
    out = []
    for i in range(6):
        pts, _ = cone_scan(np.random.default_rng(i), start_deg=(0.0, 180.0, -90.0)[i % 3],
                           direction=(1, -1)[i % 2])  # fmt: skip
        out.append(pts)
        noisy = pts.copy()
        noisy[:, 2] += rng.normal(0, 0.05, pts.shape[0]).astype(np.float32)
        out.append(noisy)
    out.append(out[0][::-1].copy())
    out.append(out[1][rng.permutation(out[1].shape[0])][:5000])
    out.append(out[2][np.abs(np.arctan2(out[2][:, 1], out[2][:, 0])) < 1.0])
    out.append(out[3].astype(np.float64))
    out.extend(
        rng.normal(size=(int(rng.integers(1, 3000)), 4)).astype(np.float32) for _ in range(8)
    )
    return out


def check_rings_and_selection(clouds):
    checked = 0
    for pts in clouds:
        for n_lasers in (None, 64, 32):
            assert np.array_equal(scan_order_rings(pts, n_lasers=n_lasers),
                                  old_scan_order_rings(pts, n_lasers))  # fmt: skip
        ring = scan_order_rings(pts, n_lasers=64)
        if int(ring[-1]) + 1 != 64:
            continue
        for far_range in (20.0, 0.0, 5.0, 60.0):
            old = old_ring_elevations(pts, ring, far_range=far_range)
            np.testing.assert_array_equal(ring_elevations(pts, ring, far_range=far_range), old)
            for n in (1, 2, 3, 4, 8, 16, 64):
                sel = select_beams(pts, ring, n=n, select="horizon", far_range=far_range)
                chosen = horizon_rings(old, n)
                assert sel.rings == chosen
                assert np.array_equal(sel.index, np.flatnonzero(np.isin(ring, chosen)))
                checked += 1
    return checked


def test_rings_and_horizon_selection_equal_the_old_code_on_synthetic_scans():
    assert check_rings_and_selection(synthetic_clouds()) > 100


@pytest.mark.real
def test_rings_and_horizon_selection_equal_the_old_code_on_real_kitti(kitti_clouds):
    clouds = [*kitti_clouds, *(c[::-1].copy() for c in kitti_clouds)]
    assert check_rings_and_selection(clouds) >= 3 * 4 * 7
    for pts in kitti_clouds:  # and on the shuffled cloud: the elevation fallback
        shuffled = pts[np.random.default_rng(0).permutation(pts.shape[0])]
        ring = recover_rings(shuffled)
        np.testing.assert_array_equal(ring_elevations(shuffled, ring),
                                      old_ring_elevations(shuffled, ring))  # fmt: skip


def test_grouped_median_equals_the_old_one_for_grouped_and_scattered_labels():
    rng = np.random.default_rng(2)
    for k in range(30):
        n = int(rng.integers(1, 4000))
        label = rng.integers(0, 64, n)
        if k % 2:
            label = np.sort(label)
        values = rng.normal(size=n)
        if k % 3 == 0:
            values = np.round(values, 1)  # ties
        new = grouped_median(values, label, 64)
        old = old_grouped_median(values, label, 64)
        np.testing.assert_array_equal(new[0], old[0])
        np.testing.assert_array_equal(new[1], old[1])


# -- JBF: row bands and threads -----------------------------------------------------------------


def jbf_scene(seed, height=90, width=160, rgb=True):
    rng = np.random.default_rng(seed)
    radar = np.zeros((height, width), np.float32)
    n = 60
    radar[rng.integers(0, height, n), rng.integers(0, width, n)] = rng.choice(
        [3.0, 7.5, 7.5, 20.0, 41.0], n
    ).astype(np.float32)  # equal depths: ties between seeds
    shape = (height // 8, width // 8, 3) if rgb else (height // 8, width // 8)
    import cv2

    guide = cv2.resize(rng.integers(0, 256, shape, dtype=np.uint8), (width, height))
    return radar, guide


@pytest.mark.parametrize("kw", [
    {}, {"kernel": "range"}, {"kernel": "spatial"}, {"conflict": "max-confidence"},
    {"range_metric": "rgb"}, {"range_metric": "rgb", "conflict": "max-confidence"},
])  # fmt: skip
def test_jbf_row_bands_give_the_serial_result_whatever_the_split(kw):
    radar, guide = jbf_scene(len(kw))
    serial = jbf.jbf_expand(radar, guide, fx=60.0, fy=60.0, threads=1, **kw)
    rows, cols, depths = jbf._seeds(radar)
    half_u, half_v = jbf._half_windows(depths, 60.0, 60.0, 2.35, 2.35)
    g = jbf._guidance_for(guide, radar.shape, kw.get("range_metric", "gray"),
                          kernel=kw.get("kernel", "jbf"))  # fmt: skip
    opts = {"sigma_s": 25.0, "sigma_r": 10.0, "threshold": 0.05,
            "kernel": kw.get("kernel", "jbf"), "conflict": kw.get("conflict", "nearest")}  # fmt: skip
    rng = np.random.default_rng(9)
    splits = [
        [0, 90],
        [0, 1, 90],
        [0, 45, 46, 90],
        [0, 89, 90],
        sorted({0, 90, *rng.integers(1, 90, 6)}),
    ]
    for edges in splits:
        out = jbf._expand(rows, cols, depths, half_u, half_v, g, edges=edges, **opts)
        assert out[0].tobytes() == serial[0].tobytes() and out[1].tobytes() == serial[1].tobytes()


def test_jbf_threads_do_not_change_the_result():
    radar, guide = jbf_scene(11, height=240, width=400)  # enough work for several bands
    base = jbf.jbf_expand(radar, guide, fx=300.0, fy=300.0, threads=1)
    assert jbf._row_bands(*_band_inputs(radar, 300.0), threads=3) is not None
    for threads in (2, 3, 5):
        out = jbf.jbf_expand(radar, guide, fx=300.0, fy=300.0, threads=threads)
        assert out[0].tobytes() == base[0].tobytes() and out[1].tobytes() == base[1].tobytes()


def _band_inputs(radar, f):
    rows, _, depths = jbf._seeds(radar)
    half_u, half_v = jbf._half_windows(depths, f, f, 2.35, 2.35)
    return rows, half_v, half_u, radar.shape[0], radar.shape[1], jbf.pruning_radius(25.0, 0.05)


def test_jbf_bands_split_the_work_evenly_and_cover_every_row():
    radar, _ = jbf_scene(12, height=240, width=400)
    edges = jbf._row_bands(*_band_inputs(radar, 300.0), threads=4)
    assert edges[0] == 0 and edges[-1] == 240 and np.all(np.diff(edges) > 0)
    assert jbf._row_bands(*_band_inputs(radar, 300.0), threads=1) is None
    tiny = np.zeros((20, 30), np.float32)
    tiny[5, 5] = 10.0
    assert jbf._row_bands(*_band_inputs(tiny, 10.0), threads=4) is None  # not worth threads


def test_jbf_uses_one_thread_in_batch_workers(monkeypatch):
    monkeypatch.setenv("NUMBA_NUM_THREADS", "1")
    assert jbf.default_threads() == 1
    monkeypatch.delenv("NUMBA_NUM_THREADS")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert jbf.default_threads() == 1
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert jbf.default_threads() == len(os.sched_getaffinity(0))


# (An integer written as text, "2", passes: the vocabulary's check_int_range reads it as the
# command line does.)
@pytest.mark.parametrize("bad", [0, -1, 1.5, "two", [2]])
def test_jbf_threads_must_be_a_positive_integer(bad):
    from sparsetools.errors import ParameterError

    radar, guide = jbf_scene(1)
    with pytest.raises((ParameterError, TypeError)):
        jbf.jbf_expand(radar, guide, fx=60.0, fy=60.0, threads=bad)
