"""ICP between scans and pose chaining (sparsetools.ops.registration)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from sparsetools.errors import DependencyError, ParameterError
from sparsetools.ops.registration import IcpResult, chain_poses, icp_pose


def rigid(yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll), written out here."""
    a, b, c = np.radians([yaw_deg, pitch_deg, roll_deg])
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rx = np.array([[1, 0, 0], [0, np.cos(c), -np.sin(c)], [0, np.sin(c), np.cos(c)]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Ry @ Rx
    T[:3, 3] = t
    return T


def pose_error(T_est, T_true) -> tuple[float, float]:
    """(translation error in metres, rotation error in degrees)."""
    E = np.linalg.inv(T_true) @ T_est
    cos = np.clip((np.trace(E[:3, :3]) - 1) / 2, -1.0, 1.0)
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(np.arccos(cos)))


def moved(points, T):
    out = points.copy()
    out[:, :3] = (points[:, :3].astype(np.float64) @ T[:3, :3].T + T[:3, 3]).astype(points.dtype)
    return out


@pytest.mark.real
def test_icp_recovers_a_known_transform_of_a_real_kitti_scan(kitti_object):
    from sparsetools.io.kitti import read_velodyne_bin

    scan = read_velodyne_bin(kitti_object / "velodyne" / "000001.bin")
    T_true = rigid(2.0, 0.3, -0.2, (0.8, -0.3, 0.05))  # about one frame of KITTI driving
    result = icp_pose(scan, moved(scan, T_true))
    assert isinstance(result, IcpResult)
    T, fitness, rmse = result  # unpacks as the brief's tuple
    dt, dr = pose_error(T, T_true)
    # Measured: 1.5 mm and 0.002 deg (fitness 1.0, RMSE 5 cm: voxel centroids of the two
    # clouds differ by up to half a voxel).
    assert dt < 0.01 and dr < 0.1, (dt, dr)
    assert fitness > 0.95 and rmse < 0.1
    # The far-field variant used for real sequences in traffic agrees.
    dt, dr = pose_error(icp_pose(scan, moved(scan, T_true), min_range=20.0)[0], T_true)
    assert dt < 0.01 and dr < 0.1, (dt, dr)


def test_icp_recovers_the_synthetic_ego_motion():
    from sparsetools.synth import Rig, ego_origin, make_textures, street_layout
    from sparsetools.synth.rig import scan_lidar

    rig = Rig.kitti()
    textures = make_textures(0)
    layout = street_layout(0, -150.0, 300.0)
    scans = [
        scan_lidar(rig, layout, textures, ego_origin(f, rig), rng=np.random.default_rng(f))[0]
        for f in (5, 6)
    ]
    # Exact answer: the ego moves 1 m along +x per frame and never turns, so a point of
    # frame 6 is at p + (1, 0, 0) in frame 5's coordinates.
    T_true = rigid(t=ego_origin(6, rig) - ego_origin(5, rig))
    r = icp_pose(scans[1], scans[0])
    dt, dr = pose_error(r.T_target_from_source, T_true)
    assert dt < 0.03 and dr < 0.1, (dt, dr)  # measured 9 mm (ring pattern on the road)
    assert 0.8 < r.fitness <= 1.0


def test_icp_identity_on_the_same_cloud():
    rng = np.random.default_rng(0)
    # A box room: six noisy planes, enough structure in every direction.
    faces = []
    for axis in range(3):
        for side in (-5.0, 5.0):
            p = rng.uniform(-5, 5, (3000, 3))
            p[:, axis] = side + rng.normal(0, 0.002, 3000)
            faces.append(p)
    room = np.vstack(faces)
    T, fitness, rmse = icp_pose(room, room, voxel=0.3, max_distance=0.5)
    dt, dr = pose_error(T, np.eye(4))
    assert dt < 1e-3 and dr < 0.01 and fitness > 0.99 and rmse < 0.01
    T_true = rigid(5.0, 1.0, -2.0, (0.4, -0.2, 0.1))
    T, _, _ = icp_pose(room, moved(room, T_true), voxel=0.3, max_distance=0.5)
    dt, dr = pose_error(T, T_true)
    assert dt < 0.01 and dr < 0.1, (dt, dr)


def test_chain_poses_composes_and_inverts():
    rng = np.random.default_rng(1)
    n = 6
    # True poses of each frame in a world frame; pairs from them.
    world = [rigid(*rng.uniform(-10, 10, 3), t=rng.uniform(-5, 5, 3)) for _ in range(n)]
    pairs = [np.linalg.inv(world[k]) @ world[k + 1] for k in range(n - 1)]
    for ref in (0, 2, n - 1):
        P = chain_poses(pairs, reference=ref)
        assert P.shape == (n, 4, 4)
        np.testing.assert_array_equal(P[ref], np.eye(4))
        for k in range(n):
            np.testing.assert_allclose(P[k], np.linalg.inv(world[ref]) @ world[k], atol=1e-9)
        # Consecutive poses give back the pairs.
        for k in range(n - 1):
            np.testing.assert_allclose(np.linalg.inv(P[k]) @ P[k + 1], pairs[k], atol=1e-9)
    assert chain_poses([], reference=0).shape == (1, 4, 4)


def test_bad_arguments():
    pts = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(ParameterError, match="at least 10"):
        icp_pose(pts[:5], pts)
    with pytest.raises(ParameterError, match="beyond min_range"):
        icp_pose(pts, pts, min_range=100.0)
    with pytest.raises(ParameterError, match="--target-points: must have shape"):
        icp_pose(pts, pts[:, :2])
    with pytest.raises(ParameterError, match="--init: holds NaN"):
        icp_pose(pts, pts, init=np.full((4, 4), np.nan))
    with pytest.raises(ParameterError, match="rigid"):
        icp_pose(pts, pts, init=np.diag([2.0, 1, 1, 1]))
    for kw in ({"voxel": 0}, {"max_distance": -1}, {"max_iterations": 0}, {"tukey_k": np.nan}):
        with pytest.raises(ParameterError):
            icp_pose(pts, pts, **kw)
    with pytest.raises(ParameterError, match="reference"):
        chain_poses([np.eye(4)], reference=2)
    with pytest.raises(ParameterError):
        chain_poses([np.ones((4, 4))])


def test_missing_open3d_is_a_dependency_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d -> ImportError
    pts = np.random.default_rng(0).normal(size=(100, 3))
    with pytest.raises(DependencyError, match="Open3D"):
        icp_pose(pts, pts)


def test_scans_open3d_cannot_register_are_a_clear_error_not_an_internal_one():
    """Open3D refuses clouds spread over 1e30 m (its voxel grid overflows): one ParameterError
    naming why, never Open3D's RuntimeError (which the command line reports as a bug)."""
    from sparsetools.errors import ParameterError
    from sparsetools.ops.registration import icp_pose

    far = np.random.default_rng(0).normal(size=(100, 3)) * 1e30
    with pytest.raises(ParameterError, match="ICP cannot register these scans: voxel_size"):
        icp_pose(far, far)
