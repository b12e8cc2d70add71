"""EffisDepth D2S / S2D: numpy and torch, exact round trips, against a loop reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sparsetools.errors import ParameterError
from sparsetools.ops.sparse import dense_to_sparse, infer_channels_last, sparse_to_dense


def reference_d2s(bhwc: np.ndarray):
    """Straightforward loop over pixels (the paper's eq. 2 read literally, any channel != 0)."""
    coords, feats = [], []
    B, H, W, C = bhwc.shape
    for b in range(B):
        for y in range(H):
            for x in range(W):
                f = bhwc[b, y, x]
                if any(v != 0 or v != v for v in f):  # v != v: NaN
                    coords.append([x, y, b])
                    feats.append(f.copy())
    return (
        np.array(coords, dtype=np.int64).reshape(-1, 3),
        np.array(feats, dtype=bhwc.dtype).reshape(-1, C),
    )


def sparse_batch(rng, shape, density=0.2, dtype=np.float32):
    x = rng.normal(size=shape).astype(dtype)
    keep = rng.random(shape[:3]) < density
    return np.where(keep[..., None], x, 0).astype(dtype)


# -- numpy -----------------------------------------------------------------------------------------
def test_matches_loop_reference_channels_last():
    rng = np.random.default_rng(0)
    x = sparse_batch(rng, (3, 7, 9, 2))
    x[1, 0, 0] = [0, 5]  # one channel non-zero is enough
    x[2, 6, 8] = [-1, 0]  # negative values are kept (exact round trip)
    coords, feats = dense_to_sparse(x, channels_last=True)
    rc, rf = reference_d2s(x)
    assert coords.dtype == np.int64 and feats.dtype == np.float32
    np.testing.assert_array_equal(coords, rc)
    np.testing.assert_array_equal(feats, rf)
    assert [0, 0, 1] in coords.tolist() and [8, 6, 2] in coords.tolist()  # image corners


def test_channels_first_gives_same_sparse_tensor():
    rng = np.random.default_rng(1)
    x = sparse_batch(rng, (2, 6, 10, 3))
    c1, f1 = dense_to_sparse(x, channels_last=True)
    c2, f2 = dense_to_sparse(np.moveaxis(x, 3, 1), channels_last=False)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(f1, f2)
    back = sparse_to_dense(c2, f2, (2, 3, 6, 10), channels_last=False)
    np.testing.assert_array_equal(back, np.moveaxis(x, 3, 1))


def test_depth_batch_three_dims_and_paper_validity():
    depth = np.zeros((2, 4, 5), np.float32)
    depth[0, 1, 2] = 12.5
    depth[1, 3, 4] = 0.25
    coords, feats = dense_to_sparse(depth)
    assert coords.tolist() == [[2, 1, 0], [4, 3, 1]]
    assert feats.shape == (2, 1) and feats[:, 0].tolist() == [12.5, 0.25]
    back = sparse_to_dense(coords, feats, depth.shape)
    assert back.shape == depth.shape and back.tobytes() == depth.tobytes()
    # 1-D features are accepted for one channel
    np.testing.assert_array_equal(sparse_to_dense(coords, feats[:, 0], depth.shape), depth)


def test_empty_batch_and_empty_sparse_tensor():
    x = np.zeros((2, 3, 4, 2), np.float64)
    coords, feats = dense_to_sparse(x, channels_last=True)
    assert coords.shape == (0, 3) and feats.shape == (0, 2) and feats.dtype == np.float64
    back = sparse_to_dense(coords, feats, x.shape)
    assert back.shape == x.shape and not back.any()


def test_nan_is_valid_and_survives():
    x = np.zeros((1, 2, 2, 1), np.float32)
    x[0, 1, 0, 0] = np.nan
    coords, feats = dense_to_sparse(x, channels_last=True)
    assert coords.tolist() == [[0, 1, 0]]
    back = sparse_to_dense(coords, feats, x.shape)
    assert back.tobytes() == x.tobytes()


def test_negative_zero_feature_of_valid_pixel_is_kept_bitwise():
    x = np.array([[[[1.0, -0.0]]], [[[-0.0, -0.0]]]], dtype=np.float32)  # (2, 1, 1, 2)
    coords, feats = dense_to_sparse(x, channels_last=True)
    assert coords.tolist() == [[0, 0, 0]]  # the all-(-0.0) pixel is empty
    back = sparse_to_dense(coords, feats, x.shape)
    assert back[0].tobytes() == x[0].tobytes()
    assert back[1].tobytes() == np.zeros((1, 1, 2), np.float32).tobytes()


def test_explicit_mask():
    x = np.arange(12, dtype=np.float32).reshape(1, 3, 4, 1)
    mask = np.zeros((1, 3, 4), bool)
    mask[0, 0, 0] = True  # a zero feature that is declared valid
    mask[0, 2, 3] = True
    coords, feats = dense_to_sparse(x, mask=mask, channels_last=True)
    assert coords.tolist() == [[0, 0, 0], [3, 2, 0]]
    assert feats[:, 0].tolist() == [0.0, 11.0]
    with pytest.raises(ParameterError, match="mask"):
        dense_to_sparse(x, mask=np.zeros((1, 3, 3), bool), channels_last=True)


def test_integer_dtypes_round_trip():
    rng = np.random.default_rng(3)
    x = rng.integers(-3, 3, size=(2, 5, 6, 4)).astype(np.int16)
    coords, feats = dense_to_sparse(x, channels_last=True)
    assert feats.dtype == np.int16
    np.testing.assert_array_equal(sparse_to_dense(coords, feats, x.shape), x)


def test_layout_inference():
    assert infer_channels_last((2, 64, 128, 3), None) is True
    assert infer_channels_last((2, 1, 64, 128), None) is False
    assert infer_channels_last((2, 3, 4, 5), True) is True
    with pytest.raises(ParameterError, match="channels_last"):
        infer_channels_last((2, 3, 8, 3), None)
    with pytest.raises(ParameterError, match="channels_last"):
        infer_channels_last((2, 16, 8, 32), None)
    with pytest.raises(ParameterError, match="channels_last"):
        dense_to_sparse(np.zeros((1, 2, 2, 2)))


def test_bad_shapes_and_coords():
    with pytest.raises(ParameterError):
        dense_to_sparse(np.zeros((4, 4)))
    coords = np.array([[0, 0, 0], [4, 0, 0]])
    feats = np.ones((2, 1), np.float32)
    with pytest.raises(ParameterError, match="outside"):
        sparse_to_dense(coords, feats, (1, 3, 4))  # x = 4 >= W
    with pytest.raises(ParameterError, match="outside"):
        sparse_to_dense(np.array([[0, 0, -1]]), feats[:1], (1, 3, 4))
    with pytest.raises(ParameterError, match="feats"):
        sparse_to_dense(coords[:1], np.ones((1, 2)), (1, 3, 4))
    with pytest.raises(ParameterError, match="coords"):
        sparse_to_dense(np.zeros((2, 2)), feats, (1, 3, 4))
    with pytest.raises(ParameterError, match="--coords: must be signed integer"):
        sparse_to_dense(np.zeros((2, 3)), feats, (1, 3, 4))
    with pytest.raises(ParameterError, match=r"--shape: must have shape \(B, H, W\)"):
        sparse_to_dense(coords, feats, (3, 4))
    with pytest.raises(ParameterError, match=r"--batch: must have shape \(B, H, W\)"):
        dense_to_sparse(np.zeros((4, 4)))


def without_empty_negative_zero(x: np.ndarray, channels_last: bool) -> np.ndarray:
    """Exact up to the sign of zero in EMPTY pixels: all channels -0.0 come back as +0.0."""
    axis = 3 if channels_last else 1
    empty = np.all(x == 0, axis=axis, keepdims=True)
    return np.where(empty, np.zeros_like(x), x)


@st.composite
def batches(draw):
    b = draw(st.integers(1, 3))
    h = draw(st.integers(1, 6))
    w = draw(st.integers(1, 6))
    c = draw(st.integers(1, 3))
    dtype = draw(st.sampled_from([np.float32, np.float64, np.int32]))
    elements = (
        st.floats(width=32 if dtype == np.float32 else 64, allow_nan=True, allow_infinity=True)
        if dtype != np.int32
        else st.integers(-5, 5)
    )
    x = draw(hnp.arrays(dtype, (b, h, w, c), elements=st.one_of(st.just(0), elements)))
    return x


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(batches(), st.booleans())
def test_round_trip_is_exact_hypothesis(x, channels_last):
    dense = x if channels_last else np.moveaxis(x, 3, 1).copy()
    coords, feats = dense_to_sparse(dense, channels_last=channels_last)
    back = sparse_to_dense(coords, feats, dense.shape, channels_last=channels_last)
    assert back.dtype == dense.dtype and back.shape == dense.shape
    assert back.tobytes() == without_empty_negative_zero(dense, channels_last).tobytes()
    rc, rf = reference_d2s(x)
    np.testing.assert_array_equal(coords, rc)
    assert feats.tobytes() == rf.tobytes()


def test_torch_refused_by_numpy_version():
    with pytest.raises(ParameterError, match="train.sparse"):
        dense_to_sparse(torch.zeros(1, 2, 2))


# -- torch -----------------------------------------------------------------------------------------
from sparsetools.train import sparse as tsparse  # noqa: E402


def test_torch_matches_numpy():
    rng = np.random.default_rng(5)
    x = sparse_batch(rng, (3, 8, 11, 2))
    c_np, f_np = dense_to_sparse(x, channels_last=True)
    c_t, f_t = tsparse.dense_to_sparse(torch.from_numpy(x), channels_last=True)
    assert c_t.dtype == torch.int64 and f_t.dtype == torch.float32
    np.testing.assert_array_equal(c_t.numpy(), c_np)
    np.testing.assert_array_equal(f_t.numpy(), f_np)
    nchw = torch.from_numpy(np.moveaxis(x, 3, 1).copy())
    c2, f2 = tsparse.dense_to_sparse(nchw, channels_last=False)
    np.testing.assert_array_equal(c2.numpy(), c_np)
    back = tsparse.sparse_to_dense(c2, f2, tuple(nchw.shape), channels_last=False)
    assert torch.equal(back, nchw)
    back_np = tsparse.sparse_to_dense(c_t, f_t, x.shape).numpy()
    assert back_np.tobytes() == x.tobytes()


def test_torch_depth_and_gradients():
    depth = torch.zeros(2, 1, 5, 6)
    depth[0, 0, 4, 5] = 3.0
    depth[1, 0, 0, 0] = 7.0
    coords, feats = tsparse.dense_to_sparse(depth, channels_last=False)
    assert coords.tolist() == [[5, 4, 0], [0, 0, 1]]
    w = torch.tensor([[2.0], [3.0]], requires_grad=True)
    out = tsparse.sparse_to_dense(coords, feats * w, (2, 1, 5, 6), channels_last=False)
    out.sum().backward()
    assert w.grad.tolist() == [[3.0], [7.0]]
    src = torch.zeros(1, 3, 3, requires_grad=True)
    dense = src + torch.tensor([[[0, 1.0, 0], [0, 0, 0], [2.0, 0, 0]]])
    _c, f = tsparse.dense_to_sparse(dense)
    f.sum().backward()  # gradient reaches only the gathered pixels
    assert src.grad.tolist() == [[[0, 1, 0], [0, 0, 0], [1, 0, 0]]]


def test_torch_empty_and_errors():
    c, f = tsparse.dense_to_sparse(torch.zeros(2, 4, 4, 1), channels_last=True)
    assert tuple(c.shape) == (0, 3) and tuple(f.shape) == (0, 1)
    assert not tsparse.sparse_to_dense(c, f, (2, 4, 4, 1)).any()
    with pytest.raises(ParameterError, match="outside"):
        tsparse.sparse_to_dense(torch.tensor([[4, 0, 0]]), torch.ones(1, 1), (1, 4, 4, 1))
    with pytest.raises(ParameterError, match="torch.Tensor"):
        tsparse.dense_to_sparse(np.zeros((1, 2, 2)))
    with pytest.raises(ParameterError, match="channels_last"):
        tsparse.dense_to_sparse(torch.zeros(1, 3, 2, 3))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(batches())
def test_torch_round_trip_hypothesis(x):
    t = torch.from_numpy(x)
    coords, feats = tsparse.dense_to_sparse(t, channels_last=True)
    back = tsparse.sparse_to_dense(coords, feats, tuple(t.shape)).numpy()
    assert back.tobytes() == without_empty_negative_zero(x, True).tobytes()
    c_np, _ = dense_to_sparse(x, channels_last=True)
    np.testing.assert_array_equal(coords.numpy(), c_np)
