"""Self-supervised geometry: rotations, pose format, projection and the view-synthesis warp."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sparsetools.errors import ParameterError
from sparsetools.train.selfsup.geometry import (
    axis_angle_to_matrix,
    backproject,
    invert_transform,
    matrix_to_axis_angle,
    pose_vector_to_matrix,
    project,
    warp_frame,
)
from sparsetools.train.selfsup.pose_net import POSE_SCALE, PoseNet, source_transforms
from test_selfsup_scene import intrinsics, pose, render, video


def rodrigues_reference(v: np.ndarray) -> np.ndarray:
    """R = cos t I + sin t [a]_x + (1 - cos t) a a^T, written out for one vector."""
    t = np.linalg.norm(v)
    if t == 0:
        return np.eye(3)
    a = v / t
    ax = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.cos(t) * np.eye(3) + np.sin(t) * ax + (1 - np.cos(t)) * np.outer(a, a)


def random_axis_angles(rng, n, lo, hi):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return axes * rng.uniform(lo, hi, (n, 1))


# -- rotations --------------------------------------------------------------------------------------
def test_axis_angle_to_matrix_matches_rodrigues():
    rng = np.random.default_rng(0)
    v = np.concatenate([random_axis_angles(rng, 20, 1e-6, 3.1), np.zeros((1, 3))])
    R = axis_angle_to_matrix(torch.from_numpy(v)).numpy()
    for k in range(len(v)):
        np.testing.assert_allclose(R[k], rodrigues_reference(v[k]), atol=1e-12)
    # rotations: orthonormal with determinant +1
    np.testing.assert_allclose(
        np.einsum("bji,bjk->bik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # right-handed: +90 degrees about z takes x to y
    Rz = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, np.pi / 2]], dtype=torch.float64))[0].numpy()
    np.testing.assert_allclose(Rz @ [1, 0, 0], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize(
    "lo,hi", [(1e-9, 1e-5), (1e-3, 1.0), (1.0, 3.0), (np.pi - 1e-4, np.pi - 1e-7)]
)
def test_axis_angle_round_trip(lo, hi):
    rng = np.random.default_rng(1)
    v = torch.from_numpy(random_axis_angles(rng, 50, lo, hi))
    back = matrix_to_axis_angle(axis_angle_to_matrix(v))
    torch.testing.assert_close(back, v, atol=1e-7 if hi > 3 else 1e-10, rtol=0)
    # and matrix -> axis-angle -> matrix
    R = axis_angle_to_matrix(v)
    torch.testing.assert_close(axis_angle_to_matrix(matrix_to_axis_angle(R)), R, atol=1e-9, rtol=0)


def test_axis_angle_gradient_is_finite_at_zero():
    v = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    axis_angle_to_matrix(v).sum().backward()
    assert torch.isfinite(v.grad).all()
    # identity
    torch.testing.assert_close(
        axis_angle_to_matrix(v.detach()), torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    )


def test_bad_shapes():
    with pytest.raises(ParameterError):
        axis_angle_to_matrix(torch.zeros(3))
    with pytest.raises(ParameterError):
        matrix_to_axis_angle(torch.zeros(2, 4, 4))
    with pytest.raises(ParameterError):
        pose_vector_to_matrix(torch.zeros(2, 3), torch.zeros(3, 3))


# -- pose format -----------------------------------------------------------------------------------
def test_pose_vector_to_matrix_and_inverse():
    rng = np.random.default_rng(2)
    aa = torch.from_numpy(random_axis_angles(rng, 8, 0.0, 0.5))
    t = torch.from_numpy(rng.normal(size=(8, 3)))
    T = pose_vector_to_matrix(aa, t)
    for k in range(8):
        ref = np.eye(4)
        ref[:3, :3] = rodrigues_reference(aa[k].numpy())
        ref[:3, 3] = t[k].numpy()
        np.testing.assert_allclose(T[k].numpy(), ref, atol=1e-12)
    Tinv = pose_vector_to_matrix(aa, t, invert=True)
    eye = torch.eye(4, dtype=torch.float64).expand(8, 4, 4)
    torch.testing.assert_close(Tinv @ T, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(T @ Tinv, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(invert_transform(T), Tinv, atol=1e-12, rtol=0)
    # 4x4 -> (axis-angle, translation) -> 4x4
    torch.testing.assert_close(matrix_to_axis_angle(T[:, :3, :3]), aa, atol=1e-10, rtol=0)
    torch.testing.assert_close(T[:, :3, 3], t)


def test_pose_net_output_format_round_trips_to_4x4():
    torch.manual_seed(0)
    net = PoseNet(width=2).double()
    a, b = (
        torch.rand(3, 3, 32, 48, dtype=torch.float64),
        torch.rand(3, 3, 32, 48, dtype=torch.float64),
    )
    aa, t = net(a, b)
    assert aa.shape == t.shape == (3, 3)
    T = net.transform(a, b)
    assert T.shape == (3, 4, 4)
    torch.testing.assert_close(
        T[:, 3], torch.tensor([0, 0, 0, 1.0], dtype=torch.float64).expand(3, 4)
    )
    torch.testing.assert_close(matrix_to_axis_angle(T[:, :3, :3]), aa, atol=1e-12, rtol=0)
    torch.testing.assert_close(T[:, :3, 3], t)
    # the head's raw output is scaled by 0.01: a zero head with bias b outputs 0.01 b
    with torch.no_grad():
        net.head.weight.zero_()
        net.head.bias.copy_(torch.arange(1.0, 7.0, dtype=torch.float64))
    aa, t = net(a, b)
    torch.testing.assert_close(
        aa, POSE_SCALE * torch.tensor([1.0, 2, 3], dtype=torch.float64).expand(3, 3)
    )
    torch.testing.assert_close(
        t, POSE_SCALE * torch.tensor([4.0, 5, 6], dtype=torch.float64).expand(3, 3)
    )


def test_previous_frame_transform_is_the_inverse():
    torch.manual_seed(1)
    net = PoseNet(width=2).double()
    prev, tgt, nxt = (torch.rand(2, 3, 32, 32, dtype=torch.float64) for _ in range(3))
    t_prev, t_next = source_transforms(net, prev, tgt, nxt)
    eye = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    # the network sees (t-1, t) in time order; T_t->t-1 is the inverse of its output
    torch.testing.assert_close(t_prev @ net.transform(prev, tgt), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(t_next, net.transform(tgt, nxt))


# -- projection and warping ------------------------------------------------------------------------
def test_backproject_project_round_trip():
    h, w = 6, 9
    K = torch.from_numpy(intrinsics(h, w))[None]
    depth = torch.from_numpy(np.random.default_rng(3).uniform(1, 50, (1, 1, h, w)))
    pts = backproject(depth, K)
    torch.testing.assert_close(pts[:, 2], depth.reshape(1, -1))  # camera z is the depth
    uv, z = project(pts, K, torch.eye(4, dtype=torch.float64)[None])
    v, u = np.mgrid[0:h, 0:w]
    np.testing.assert_allclose(uv[0, 0].numpy(), u.ravel(), atol=1e-10)
    np.testing.assert_allclose(uv[0, 1].numpy(), v.ravel(), atol=1e-10)
    torch.testing.assert_close(z[:, 0], depth.reshape(1, -1))


def test_warp_coordinates_match_a_reference_projection():
    """A source that is linear in (u, v) is sampled exactly by bilinear interpolation, so the
    warped image must equal that linear function at the reference projection of each pixel."""
    h, w = 12, 16
    K = intrinsics(h, w)
    rng = np.random.default_rng(4)
    depth = rng.uniform(8, 20, (h, w))
    T = np.eye(4)
    T[:3, :3] = rodrigues_reference(np.array([0.01, -0.02, 0.005]))
    T[:3, 3] = [0.1, -0.05, -0.3]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    # reference, written out: p_s ~ K T D K^-1 p
    P = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)]) * depth.ravel()
    Ps = T[:3, :3] @ P + T[:3, 3:]
    ps = K @ Ps
    us, vs = ps[0] / ps[2], ps[1] / ps[2]
    a, b, c = 0.01, 0.02, 0.1
    source = (a * u + b * v + c)[None, None]
    warp = warp_frame(
        torch.from_numpy(source),
        torch.from_numpy(depth)[None, None],
        torch.from_numpy(T)[None],
        torch.from_numpy(K)[None],
    )
    inside = warp.inside[0, 0].numpy().ravel()
    assert inside.mean() > 0.6
    got = warp.image[0, 0].numpy().ravel()
    np.testing.assert_allclose(got[inside], (a * us + b * vs + c)[inside], atol=1e-12)
    # outside the image: border padding clamps the coordinates
    uc, vc = np.clip(us, 0, w - 1), np.clip(vs, 0, h - 1)
    np.testing.assert_allclose(got[~inside], (a * uc + b * vc + c)[~inside], atol=1e-12)


def test_identity_warp_returns_the_source():
    rng = np.random.default_rng(5)
    src = torch.from_numpy(rng.random((2, 3, 7, 10)))
    K = torch.from_numpy(intrinsics(7, 10)).expand(2, 3, 3)
    warp = warp_frame(
        src,
        torch.full((2, 1, 7, 10), 4.0, dtype=torch.float64),
        torch.eye(4, dtype=torch.float64).expand(2, 4, 4),
        K,
    )
    torch.testing.assert_close(warp.image, src, atol=1e-12, rtol=0)
    assert bool(warp.in_front.all()) and bool(warp.inside.all())


def test_points_behind_the_source_camera_are_not_warped():
    h, w = 8, 8
    K = torch.from_numpy(intrinsics(h, w))[None]
    T = torch.eye(4, dtype=torch.float64)[None].clone()
    T[0, 2, 3] = -10.0  # the source camera is 10 m ahead of points at 5 m
    warp = warp_frame(
        torch.rand(1, 3, h, w, dtype=torch.float64),
        torch.full((1, 1, h, w), 5.0, dtype=torch.float64),
        T,
        K,
    )
    assert not bool(warp.in_front.any()) and not bool(warp.inside.any())
    assert torch.isfinite(warp.image).all()
    with pytest.raises(ParameterError, match="2x2"):
        warp_frame(torch.rand(1, 3, 1, 5), torch.ones(1, 1, 1, 5), T.float(), K.float())


def test_true_depth_and_pose_reconstruct_the_target_of_a_plane_scene():
    """Warping a rendered source frame with the TRUE depth and pose gives the target frame
    wherever the target's point is seen in the source away from texture seams and sky edges
    (the street canyon is convex from inside: nothing is occluded, nothing moves)."""
    h, w = 64, 96
    K = intrinsics(h, w)
    T_t, T_s = pose(0.0), pose(1.0, yaw=0.02, x=0.2)  # camera-to-world of target and source
    target, depth_t, label_t = render(K, T_t, h, w, labels=True)
    source, _, label_s = render(K, T_s, h, w, labels=True)
    T_t_to_s = np.linalg.inv(T_s) @ T_t
    warp = warp_frame(
        torch.from_numpy(source.transpose(2, 0, 1))[None],
        torch.from_numpy(depth_t)[None, None],
        torch.from_numpy(T_t_to_s)[None],
        torch.from_numpy(K)[None],
    )
    # where each target pixel lands in the source (reference projection)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    P = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(h * w)]) * depth_t.ravel()
    Ps = T_t_to_s[:3, :3] @ P + T_t_to_s[:3, 3:]
    us, vs = (K @ Ps)[:2] / Ps[2]
    ok = warp.inside[0, 0].numpy().ravel() & (label_t.ravel() >= 0)
    # the four pixels bilinear interpolation reads show the same surface
    for du in (0, 1):
        for dv in (0, 1):
            ui = np.clip(np.floor(us) + du, 0, w - 1).astype(int)
            vi = np.clip(np.floor(vs) + dv, 0, h - 1).astype(int)
            ok &= label_s[vi, ui] == label_t.ravel()
    assert ok.mean() > 0.6
    err = np.abs(warp.image[0].numpy().reshape(3, -1) - target.reshape(-1, 3).T)[:, ok]
    # rendering noise only: bilinear interpolation of a smooth texture
    assert np.median(err) < 0.002 and np.percentile(err, 99) < 0.02 and err.max() < 0.06
    # while a wrong depth does not reconstruct it
    wrong = warp_frame(
        torch.from_numpy(source.transpose(2, 0, 1))[None],
        torch.from_numpy(depth_t * 0.5)[None, None],
        torch.from_numpy(T_t_to_s)[None],
        torch.from_numpy(K)[None],
    )
    err_wrong = np.abs(wrong.image[0].numpy().reshape(3, -1) - target.reshape(-1, 3).T)[:, ok]
    assert np.median(err_wrong) > 5 * np.median(err)


def test_video_helper_frames_reconstruct_with_true_poses():
    frames = video(3, 48, 64, speed=0.8)
    t, s = frames[1], frames[2]
    warp = warp_frame(
        torch.from_numpy(s.rgb.transpose(2, 0, 1).astype(np.float64) / 255)[None],
        torch.from_numpy(t.depth.astype(np.float64))[None, None],
        torch.from_numpy(np.linalg.inv(s.T_world_cam) @ t.T_world_cam)[None],
        torch.from_numpy(t.K)[None],
    )
    ok = warp.inside[0, 0].numpy() & (t.depth > 0)
    err = np.abs(warp.image[0].numpy().transpose(1, 2, 0) - t.rgb / 255.0)[ok]
    assert np.median(err) < 0.01  # uint8 quantisation + bilinear interpolation


def test_true_depth_and_pose_reconstruct_a_synthetic_video_frame():
    """The same with the street-video generator (sparsetools.synth.video): static pixels that
    the source sees unoccluded are reconstructed to rendering noise."""
    from sparsetools.synth import video as video_mod

    seq = video_mod.simulate_video(3, n_frames=3, image_size=(208, 64), lidar=False)
    t, s = seq.frames[1], seq.frames[2]
    h, w = t.depth.shape
    T = np.linalg.inv(s.T_world_from_cam) @ t.T_world_from_cam
    warp = warp_frame(
        torch.from_numpy(s.image.transpose(2, 0, 1) / 255.0)[None],
        torch.from_numpy(t.depth.astype(np.float64))[None, None],
        torch.from_numpy(T)[None],
        torch.from_numpy(t.K)[None],
    )
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    P = np.linalg.inv(t.K) @ np.stack([u.ravel(), v.ravel(), np.ones(h * w)]) * t.depth.ravel()
    Ps = T[:3, :3] @ P + T[:3, 3:]
    us, vs = (t.K @ Ps)[:2] / Ps[2]
    ui = np.clip(np.rint(us), 0, w - 1).astype(int)
    vi = np.clip(np.rint(vs), 0, h - 1).astype(int)
    ok = warp.inside[0, 0].numpy().ravel() & (t.depth.ravel() > 0) & ~t.moving_mask.ravel()
    ok &= np.abs(s.depth[vi, ui] - Ps[2]) < 0.02 * Ps[2]  # not occluded in the source
    ok &= ~s.moving_mask[vi, ui]
    assert ok.mean() > 0.5
    target = (t.image / 255.0).reshape(-1, 3).T
    err = np.abs(warp.image[0].numpy().reshape(3, -1) - target)[:, ok]
    identity = np.abs((s.image / 255.0).reshape(-1, 3).T - target)[:, ok]
    assert np.median(err) < 0.002 and np.percentile(err, 90) < 0.03
    assert np.median(err) < 0.25 * np.median(identity)
