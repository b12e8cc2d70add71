"""sparsetools.ops.projection: exactness against independent references, properties, edges."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sparsetools.calibration import Calibration
from sparsetools.errors import ParameterError
from sparsetools.ops.projection import (
    accumulate_sweeps,
    nuscenes_T_cam_from_sensor,
    project_points,
    project_points_with_index,
    project_uvz,
    rigid_inverse,
    sparse_from_depth,
)

# -- independent references written for the tests ---------------------------------------------


def reference_depth(points, M, width, height, *, min_depth=0.1, max_depth=np.inf, offset=0):
    """Straightforward z-buffer: project all, filter, np.minimum.at per pixel (half-to-even)."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    uvw = xyz @ np.asarray(M)[:, :3].T + np.asarray(M)[:, 3]
    z = uvw[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = (z > min_depth) & (z <= max_depth)
        u = np.round(uvw[:, 0] / z) + offset
        v = np.round(uvw[:, 1] / z) + offset
        keep &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
    buf = np.full(width * height, np.inf)
    np.minimum.at(buf, v[keep].astype(np.int64) * width + u[keep].astype(np.int64), z[keep])
    out = np.where(np.isfinite(buf), buf, 0.0).astype(np.float32).reshape(height, width)
    return out, int(keep.sum())


def reference_index(points, M, width, height, *, min_depth=0.1):
    """Winner per pixel by sorting (pixel, depth, x, y, z, index) with np.lexsort."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    uvw = xyz @ np.asarray(M)[:, :3].T + np.asarray(M)[:, 3]
    z = uvw[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.round(uvw[:, 0] / z)
        v = np.round(uvw[:, 1] / z)
        keep = (z > min_depth) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    idx = np.flatnonzero(keep)
    pix = v[idx].astype(np.int64) * width + u[idx].astype(np.int64)
    p = np.asarray(points, dtype=np.float64)
    order = np.lexsort((idx, p[idx, 2], p[idx, 1], p[idx, 0], z[idx], pix))
    pix, idx = pix[order], idx[order]
    first = np.ones(pix.shape[0], dtype=bool)
    first[1:] = pix[1:] != pix[:-1]
    out = np.full(width * height, -1, dtype=np.int64)
    out[pix[first]] = idx[first]
    return out.reshape(height, width)


def kitti_projection_from_file(path):
    """P2 @ R0_rect @ Tr_velo_to_cam parsed here, independently of sparsetools.io."""
    vals = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            vals[k.strip()] = np.array(v.split(), dtype=np.float64)
    R0 = np.eye(4)
    R0[:3, :3] = vals["R0_rect"].reshape(3, 3)
    Tr = np.eye(4)
    Tr[:3, :4] = vals["Tr_velo_to_cam"].reshape(3, 4)
    return vals["P2"].reshape(3, 4) @ R0 @ Tr


def monodepth2_depth(velo, P_velo2im, width, height):
    """monodepth2's generate_depth_map algorithm (METHODS.md section 1), re-written:
    drop Velodyne x < 0, project with P_rect @ R_rect @ velo2cam, round (numpy, half to even)
    and subtract 1, keep 0 <= x < W, 0 <= y < H, assign in order (last wins), then give
    pixels hit by several points the minimum depth, and zero negative depths."""
    velo = np.asarray(velo, dtype=np.float32).copy()
    velo[:, 3] = 1.0
    velo = velo[velo[:, 0] >= 0, :]
    pts = np.dot(P_velo2im, velo.T).T
    pts[:, :2] = pts[:, :2] / pts[:, 2][..., np.newaxis]
    pts[:, 0] = np.round(pts[:, 0]) - 1
    pts[:, 1] = np.round(pts[:, 1]) - 1
    val = (pts[:, 0] >= 0) & (pts[:, 1] >= 0)
    val &= (pts[:, 0] < width) & (pts[:, 1] < height)
    pts = pts[val, :]
    depth = np.zeros((height, width))
    xs, ys = pts[:, 0].astype(int), pts[:, 1].astype(int)
    depth[ys, xs] = pts[:, 2]
    inds = ys * width + xs
    uniq, counts = np.unique(inds, return_counts=True)
    for dd in uniq[counts > 1]:
        sel = np.where(inds == dd)[0]
        depth[ys[sel[0]], xs[sel[0]]] = pts[sel, 2].min()
    depth[depth < 0] = 0
    return depth


def simple_calib(width=40, height=30, f=20.0, cx=None, cy=None, T=None):
    cx = (width - 1) / 2 if cx is None else cx
    cy = (height - 1) / 2 if cy is None else cy
    K = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]])
    return Calibration(
        K=K, T_cam_from_sensor=np.eye(4) if T is None else T, width=width, height=height
    )


def random_rigid(rng):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    T[:3, 3] = rng.normal(0, 2, 3)
    return T


# -- real KITTI and nuScenes frames -------------------------------------------------------------


SAMPLE_KITTI = Path(__file__).resolve().parent.parent / "sample_data" / "kitti"


def test_bundled_kitti_frame_matches_reference_and_monodepth2():
    """sample_data/kitti (real frame 000001, part of the checkout): runs without ../shared."""
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin

    points = read_velodyne_bin(SAMPLE_KITTI / "velodyne" / "000001.bin")
    calib = load_calibration(SAMPLE_KITTI / "calib" / "000001.txt", image_size=(1242, 375))
    M = kitti_projection_from_file(SAMPLE_KITTI / "calib" / "000001.txt")
    depth = project_points(points, calib)
    np.testing.assert_array_equal(depth, reference_depth(points, M, 1242, 375)[0])
    assert np.count_nonzero(depth) == 18600
    md2 = monodepth2_depth(points, M, 1242, 375).astype(np.float32)
    np.testing.assert_array_equal(project_points(points, calib, pixel_offset=-1), md2)


@pytest.mark.real
@pytest.mark.parametrize("stem", ["000000", "000001"])
def test_kitti_matches_reference_pixel_for_pixel(kitti_object, stem):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import image_header_size
    from sparsetools.io.kitti import read_velodyne_bin

    size = image_header_size((kitti_object / "image_2" / f"{stem}.png").read_bytes())
    points = read_velodyne_bin(kitti_object / "velodyne" / f"{stem}.bin")
    calib = load_calibration(kitti_object / "calib" / f"{stem}.txt", image_size=size)
    M = kitti_projection_from_file(kitti_object / "calib" / f"{stem}.txt")
    np.testing.assert_allclose(calib.projection, M, rtol=0, atol=1e-12)
    depth, n_in = project_points(points, calib, return_count=True)
    ref, n_ref = reference_depth(points, M, *size)
    assert depth.shape == (size[1], size[0]) and depth.dtype == np.float32
    np.testing.assert_array_equal(depth, ref)
    assert n_in == n_ref
    assert 15000 < np.count_nonzero(depth) < 25000  # ~18.6k valid pixels on 000001
    # Nothing behind the camera or beyond the scanner's range.
    assert depth[depth > 0].min() > 0.1 and depth.max() < 130


@pytest.mark.real
@pytest.mark.parametrize("stem", ["000000", "000001"])
def test_kitti_matches_monodepth2_with_offset(kitti_object, stem):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.image import image_header_size
    from sparsetools.io.kitti import read_velodyne_bin

    size = image_header_size((kitti_object / "image_2" / f"{stem}.png").read_bytes())
    points = read_velodyne_bin(kitti_object / "velodyne" / f"{stem}.bin")
    calib = load_calibration(kitti_object / "calib" / f"{stem}.txt", image_size=size)
    M = kitti_projection_from_file(kitti_object / "calib" / f"{stem}.txt")
    md2 = monodepth2_depth(points, M, *size)
    ours = project_points(points[points[:, 0] >= 0], calib, pixel_offset=-1)
    np.testing.assert_array_equal(ours, md2.astype(np.float32))
    # The x >= 0 filter changes nothing here: those points are behind the camera anyway.
    np.testing.assert_array_equal(ours, project_points(points, calib, pixel_offset=-1))


@pytest.mark.real
def test_kitti_raw_calib_pair_gives_the_object_calib_map(real_dir, kitti_object):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.kitti import read_velodyne_bin

    points = read_velodyne_bin(kitti_object / "velodyne" / "000001.bin")
    raw = load_calibration(real_dir / "kitti-raw-calib-2011_09_26")
    obj = load_calibration(kitti_object / "calib" / "000001.txt", image_size=(1242, 375))
    assert raw.size == (1242, 375)
    a, b = project_points(points, raw), project_points(points, obj)
    np.testing.assert_array_equal(a, b)
    # The raw README's check: monodepth2 on the raw pair = this map shifted by (-1, -1).
    shifted = project_points(points, raw, pixel_offset=-1)
    np.testing.assert_array_equal(shifted[:-1, :-1], a[1:, 1:])


@pytest.mark.real
def test_nuscenes_lidar_top_devkit_count(nuscenes_demo):
    from sparsetools.io.calib import load_calibration
    from sparsetools.io.nuscenes import read_lidar_pcd_bin

    calib = load_calibration(nuscenes_demo / "calib_derived_from_pkl.json", camera="CAM_FRONT")
    cloud = next(nuscenes_demo.glob("*LIDAR_TOP*.pcd.bin"))
    points = read_lidar_pcd_bin(cloud)
    assert points.shape == (34688, 5)
    W, H = calib.size
    u, v, depth = project_uvz(points, calib.projection)
    # The devkit's map_pointcloud_to_image mask: depth > 1 m, 1 px margin, no z-buffer.
    mask = (depth > 1.0) & (u > 1) & (u < W - 1) & (v > 1) & (v < H - 1)
    assert int(mask.sum()) == 3053
    assert 4.4 < depth[mask].min() < 4.6 and 98.0 < depth[mask].max() < 98.2
    # The z-buffered map holds at most that many pixels, each the nearest of its points.
    dmap = project_points(points, calib, min_depth=1.0)
    assert 0 < np.count_nonzero(dmap) <= 3053 + 2 * (W + H)


# -- properties ---------------------------------------------------------------------------------


clouds = st.integers(0, 2**31 - 1).map(np.random.default_rng)


@settings(max_examples=40, deadline=None)
@given(rng=clouds, n=st.integers(0, 400), quantise=st.booleans())
def test_order_does_not_change_the_map(rng, n, quantise):
    calib = simple_calib(T=random_rigid(rng) if rng.random() < 0.5 else None)
    pts = rng.normal(0, 1, (n, 4)) * [3, 3, 4, 1] + [0, 0, 6, 0]
    if quantise:  # many exact duplicates and exact depth ties
        pts = np.round(pts * 2) / 2
    perm = rng.permutation(n)
    a = project_points(pts, calib)
    np.testing.assert_array_equal(a, project_points(pts[perm], calib))
    d1, i1 = project_points_with_index(pts, calib)
    d2, i2 = project_points_with_index(pts[perm], calib)
    np.testing.assert_array_equal(d1, a)
    np.testing.assert_array_equal(d2, a)
    # Index maps agree up to exact duplicate points.
    valid = i1 >= 0
    np.testing.assert_array_equal(valid, i2 >= 0)
    np.testing.assert_array_equal(pts[i1[valid], :3], pts[perm][i2[valid], :3])


@settings(max_examples=40, deadline=None)
@given(rng=clouds, n=st.integers(1, 500), offset=st.sampled_from([0, -1]))
def test_every_pixel_is_the_minimum_of_its_points(rng, n, offset):
    calib = simple_calib(
        width=int(rng.integers(1, 30)), height=int(rng.integers(1, 20)), T=random_rigid(rng)
    )
    pts = rng.normal(0, 4, (n, 3))
    pts = np.round(pts, 1) if rng.random() < 0.5 else pts
    max_depth = float(rng.uniform(1, 8)) if rng.random() < 0.5 else None
    W, H = calib.size
    depth, n_in = project_points(
        pts, calib, max_depth=max_depth, pixel_offset=offset, return_count=True
    )
    ref, n_ref = reference_depth(
        pts,
        calib.projection,
        W,
        H,
        offset=offset,
        max_depth=np.inf if max_depth is None else max_depth,
    )
    np.testing.assert_array_equal(depth, ref)
    assert n_in == n_ref
    if offset == 0 and max_depth is None:
        _, index = project_points_with_index(pts, calib)
        np.testing.assert_array_equal(index, reference_index(pts, calib.projection, W, H))


@settings(max_examples=30, deadline=None)
@given(rng=clouds, n=st.integers(1, 300))
def test_points_behind_the_camera_never_appear(rng, n):
    calib = simple_calib(T=random_rigid(rng))
    cam = rng.normal(0, 3, (n, 3))
    cam[:, 2] = -np.abs(cam[:, 2])  # camera z <= 0
    cam[rng.random(n) < 0.2, 2] = 0.0
    sensor = (cam - calib.T_cam_from_sensor[:3, 3]) @ calib.T_cam_from_sensor[:3, :3]
    depth, index = project_points_with_index(sensor, calib)
    assert not depth.any() and (index == -1).all()
    # Mixed with points in front, only the front ones are ever chosen.
    front = rng.normal(0, 1, (n, 3)) + np.array([0, 0, 5])
    both = np.vstack(
        [sensor, (front - calib.T_cam_from_sensor[:3, 3]) @ calib.T_cam_from_sensor[:3, :3]]
    )
    _, index = project_points_with_index(both, calib)
    assert (index[index >= 0] >= n).all()


def test_index_map_carries_point_fields():
    rng = np.random.default_rng(3)
    calib = simple_calib()
    pts = np.hstack([rng.normal(0, 1, (300, 3)) + np.array([0, 0, 5]), rng.random((300, 1))])
    depth, index = project_points_with_index(pts, calib)
    valid = index >= 0
    _, _, z = project_uvz(pts, calib.projection)
    np.testing.assert_array_equal(depth[valid], z[index[valid]].astype(np.float32))
    intensity = np.where(valid, pts[np.maximum(index, 0), 3], 0)
    assert intensity[valid].min() >= 0 and np.count_nonzero(intensity) <= valid.sum()


# -- edges --------------------------------------------------------------------------------------


def test_empty_and_single_point():
    calib = simple_calib(width=5, height=4, f=1.0, cx=0.0, cy=0.0)
    for empty in (np.zeros((0, 3)), np.zeros((0, 4), np.float32)):
        d, n = project_points(empty, calib, return_count=True)
        assert d.shape == (4, 5) and not d.any() and n == 0
        d, i = project_points_with_index(empty, calib)
        assert not d.any() and (i == -1).all()
    d = project_points(np.array([[2.0, 3.0, 1.0]]), calib)
    assert d[3, 2] == 1.0 and np.count_nonzero(d) == 1


def test_pixel_borders_round_half_to_even():
    # f = 1, c = 0, z = 1: u = x exactly, so the rounding rule is visible.
    calib = simple_calib(width=4, height=3, f=1.0, cx=0.0, cy=0.0)
    xs = np.array([-0.51, -0.5, 0.5, 1.5, 2.5, 3.49, 3.5])
    pts = np.column_stack([xs, np.zeros_like(xs), np.ones_like(xs)])
    _, index = project_points_with_index(pts, calib)
    # -0.51 -> out; -0.5 -> 0 (rint(-0.5) = -0); 0.5 -> 0; 1.5 -> 2; 2.5 -> 2; 3.49 -> 3;
    # 3.5 -> 4 (out). Ties at equal depth go to the smallest x.
    np.testing.assert_array_equal(index[0], [1, -1, 3, 5])
    # Exact duplicates: the smallest index, in whatever order they come.
    dup = np.array([[1.0, 0, 1, 7], [1.0, 0, 1, 3], [0.9, 0, 1, 5]])
    _, index = project_points_with_index(dup, calib)
    assert index[0, 1] == 2
    _, index = project_points_with_index(dup[:2], calib)
    assert index[0, 1] == 0
    # With pixel_offset -1 everything moves one pixel up-left: column 0 leaves the image and
    # the point at u = 3.5 (pixel 4) comes in as column 3.
    d = project_points(pts + np.array([0, 1, 0]), calib, pixel_offset=-1)
    np.testing.assert_array_equal(d[0] > 0, [False, True, True, True])


def test_depth_range_bounds_are_exclusive_below_inclusive_above():
    calib = simple_calib(width=3, height=1, f=1.0, cx=0.0, cy=0.0)
    # Depths 0.1 (dropped: depth <= min_depth), 2 and 5 (kept with max_depth 5).
    pts = np.array([[0.0, 0.0, 0.1], [2.0, 0.0, 2.0], [10.0, 0.0, 5.0], [15.0, 0.0, 5.0]])
    d = project_points(pts, calib, max_depth=5.0)
    np.testing.assert_array_equal(d[0], [0.0, 2.0, 5.0])
    d = project_points(pts, calib, min_depth=0.0, max_depth=4.9)
    np.testing.assert_array_equal(d[0], np.float32([0.1, 2.0, 0.0]))


def test_nan_and_inf_points_are_ignored():
    calib = simple_calib()
    good = np.array([[0.0, 0.0, 5.0]])
    bad = np.array(
        [
            [np.nan, 0, 5],
            [0, np.inf, 5],
            [0, 0, np.inf],
            [0, 0, -np.inf],
            [np.inf, np.inf, np.inf],
            [1e300, 0, 1e-300],
        ]
    )
    d, n = project_points(np.vstack([bad, good]), calib, return_count=True)
    np.testing.assert_array_equal(d, project_points(good, calib))
    assert n == 1
    _, i = project_points_with_index(np.vstack([bad, good]), calib)
    assert set(np.unique(i)) == {-1, len(bad)}


def test_float32_and_float64_inputs_agree():
    rng = np.random.default_rng(0)
    pts = (rng.normal(0, 3, (2000, 4)) + np.array([0, 0, 8, 0])).astype(np.float32)
    calib = simple_calib(T=random_rigid(rng))
    np.testing.assert_array_equal(
        project_points(pts, calib), project_points(pts.astype(np.float64), calib)
    )
    # Extra columns and integer input are accepted.
    np.testing.assert_array_equal(project_points(pts[:, :3], calib), project_points(pts, calib))
    ints = np.array([[0, 0, 5], [1, 1, 7]])
    assert np.count_nonzero(project_points(ints, simple_calib())) == 2


def test_bad_arguments_raise_parameter_error():
    calib = simple_calib()
    pts = np.zeros((3, 3))
    with pytest.raises(ParameterError, match="points"):
        project_points(np.zeros((3, 2)), calib)
    with pytest.raises(ParameterError, match="points"):
        project_points(np.zeros(3), calib)
    with pytest.raises(ParameterError, match="min-depth"):
        project_points(pts, calib, min_depth=-1)
    with pytest.raises(ParameterError, match="max-depth.*min-depth"):
        project_points(pts, calib, min_depth=2, max_depth=1)
    with pytest.raises(ParameterError, match="max-depth"):
        project_points(pts, calib, max_depth=float("nan"))
    with pytest.raises(ParameterError, match="image size"):
        project_points(pts, Calibration(K=np.eye(3), T_cam_from_sensor=np.eye(4)))
    with pytest.raises(ParameterError, match="Calibration"):
        project_points(pts, np.eye(3))
    with pytest.raises(ParameterError, match="pixel-offset"):
        project_points(pts, calib, pixel_offset=0.5)
    with pytest.raises(ParameterError, match="points.*numbers|points.*floating"):
        project_points(np.zeros((3, 3), bool), calib)


def test_sparse_from_depth_round_trip():
    rng = np.random.default_rng(1)
    depth = np.where(rng.random((30, 40)) < 0.1, rng.uniform(1, 300, (30, 40)), 0).astype(
        np.float32
    )
    depth[0, 0] = np.nan
    u, v, d = sparse_from_depth(depth)
    assert u.dtype == np.uint16 and v.dtype == np.uint16 and d.dtype == np.float32
    back = np.zeros_like(depth)
    back[v, u] = d
    np.testing.assert_array_equal(back, np.nan_to_num(depth, nan=0.0))
    assert np.all(np.diff(v.astype(int) * 40 + u) > 0)  # row-major order


# -- transforms and sweeps ----------------------------------------------------------------------


def test_rigid_inverse():
    rng = np.random.default_rng(2)
    T = random_rigid(rng)
    np.testing.assert_allclose(rigid_inverse(T) @ T, np.eye(4), atol=1e-12)
    with pytest.raises(ParameterError):
        rigid_inverse(np.eye(3))


def _pose(quat_wxyz, t):
    T = np.eye(4)
    w, x, y, z = quat_wxyz
    T[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
    T[:3, 3] = t
    return T


def test_nuscenes_chain_matches_point_by_point_transform():
    rng = np.random.default_rng(4)
    ego_from_sensor = _pose([0.7, 0.01, 0.0, 0.71], [3.4, 0.0, 0.5])
    global_from_ego_s = _pose([0.9, 0.0, 0.0, 0.43], [400.0, 1100.0, 0.0])
    global_from_ego_c = _pose([0.89, 0.0, 0.0, 0.45], [401.2, 1100.4, 0.01])
    ego_from_cam = _pose([0.5, -0.5, 0.5, -0.5], [1.7, 0.0, 1.5])
    pts = rng.normal(0, 20, (50, 3))
    # Step by step, as the devkit does (rotate then translate, inverse = translate then rotate).
    p = pts @ ego_from_sensor[:3, :3].T + ego_from_sensor[:3, 3]
    p = p @ global_from_ego_s[:3, :3].T + global_from_ego_s[:3, 3]
    p = (p - global_from_ego_c[:3, 3]) @ global_from_ego_c[:3, :3]
    p = (p - ego_from_cam[:3, 3]) @ ego_from_cam[:3, :3]
    T = nuscenes_T_cam_from_sensor(
        ego_from_sensor, global_from_ego_s, global_from_ego_c, ego_from_cam
    )
    np.testing.assert_allclose(pts @ T[:3, :3].T + T[:3, 3], p, atol=1e-9)


def test_accumulate_sweeps_transforms_xyz_only():
    rng = np.random.default_rng(5)
    sweeps = []
    for k in range(3):
        pts = rng.normal(0, 5, (10 + k, 18)).astype(np.float32)
        sweeps.append((pts, random_rigid(rng)))
    merged, owner = accumulate_sweeps(sweeps, return_sweep_index=True)
    assert merged.shape == (33, 18) and merged.dtype == np.float32
    np.testing.assert_array_equal(owner, np.repeat([0, 1, 2], [10, 11, 12]))
    for k, (pts, T) in enumerate(sweeps):
        mine = merged[owner == k]
        expect = (np.c_[pts[:, :3].astype(np.float64), np.ones(len(pts))] @ T.T)[:, :3]
        np.testing.assert_allclose(mine[:, :3], expect, rtol=1e-6, atol=1e-5)
        np.testing.assert_array_equal(mine[:, 3:], pts[:, 3:])  # velocities etc. untouched
    # Identity keeps the points bit for bit.
    pts = sweeps[0][0]
    np.testing.assert_array_equal(accumulate_sweeps([(pts, np.eye(4))]), pts)
    with pytest.raises(ParameterError, match="columns"):
        accumulate_sweeps([(pts, np.eye(4)), (pts[:, :4], np.eye(4))])
    with pytest.raises(ParameterError):
        accumulate_sweeps([])
