"""EffisDepth sparse tensors: dense batch <-> (coordinates, features), numpy.

A sparse tensor ``S = {C (N, 3), F (N, C)}`` keeps only the valid pixels of a batch of maps
(EffisDepth, eq. 1-3): ``C`` holds ``[x, y, b]`` (column, row, batch index) and ``F`` the
feature vector of each valid pixel. D2S (:func:`dense_to_sparse`) extracts them, S2D
(:func:`sparse_to_dense`) scatters them back into zeros; the round trip is exact.

A pixel is valid when **any** of its channels is non-zero (NaN counts as non-zero). For a
depth map (one channel, never negative) that is the paper's ``T(x, y) > 0``. Using ``!= 0``
rather than ``> 0`` is what makes the round trip exact for any input (a negative feature is
kept); the only value that does not survive bit for bit is ``-0.0``, which is an empty pixel
and comes back as ``+0.0``.

The torch versions with the same signatures are in :mod:`sparsetools.train.sparse` (torch is
imported only under ``train/``).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from ..errors import ParameterError
from ..validate import check_dtype, check_shape, check_values

__all__ = ["dense_to_sparse", "infer_channels_last", "sparse_to_dense"]

# A channel axis longer than this is not guessed from the shape alone.
_MAX_GUESSED_CHANNELS = 4


def infer_channels_last(shape: tuple[int, ...], channels_last: bool | None) -> bool:
    """Decide the layout of a 4-D batch: ``(B, H, W, C)`` (True) or ``(B, C, H, W)`` (False).

    With ``channels_last=None`` the layout is inferred only when it is unambiguous: exactly
    one of ``shape[1]`` and ``shape[3]`` is a plausible channel count (<= 4) and the other
    is not. Otherwise :class:`ParameterError` asks for ``channels_last``.
    """
    if channels_last is not None:
        return bool(channels_last)
    check_shape(SimpleNamespace(shape=shape), "(B, H, W, C) | (B, C, H, W)", "shape")
    last_small = shape[3] <= _MAX_GUESSED_CHANNELS
    first_small = shape[1] <= _MAX_GUESSED_CHANNELS
    if last_small and not first_small:
        return True
    if first_small and not last_small:
        return False
    raise ParameterError(
        f"cannot tell whether a batch of shape {tuple(shape)} is (B, H, W, C) or (B, C, H, W): "
        "pass channels_last=True or False"
    )


def _as_bhwc(batch: np.ndarray, channels_last: bool | None) -> tuple[np.ndarray, bool]:
    """View of ``batch`` as (B, H, W, C) and whether the input was 3-D (B, H, W)."""
    check_shape(batch, "(B, H, W) | (B, H, W, C) | (B, C, H, W)", "batch")
    if batch.ndim == 3:
        return batch[..., None], True
    if infer_channels_last(batch.shape, channels_last):
        return batch, False
    return np.moveaxis(batch, 1, 3), False


def dense_to_sparse(
    batch: np.ndarray,
    *,
    channels_last: bool | None = None,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """D2S: the valid pixels of a batch of maps as a sparse tensor.

    Parameters
    ----------
    batch : (B, H, W, C), (B, C, H, W) or (B, H, W) array
        Dense maps, any numeric dtype (e.g. sparse depth in metres, float32). A 3-D batch is
        one channel.
    channels_last : bool, optional
        Layout of a 4-D batch; inferred when unambiguous (see :func:`infer_channels_last`).
    mask : (B, H, W) bool, optional
        Valid pixels; default: pixels where any channel is non-zero (or NaN).

    Returns
    -------
    coords : (N, 3) int64
        ``[x, y, b]`` per valid pixel (column, row, batch index), in row-major order of
        ``(b, y, x)``.
    feats : (N, C) array, dtype of ``batch``
        The feature vector of each valid pixel.
    """
    if type(batch).__module__.startswith("torch"):
        raise ParameterError("use sparsetools.train.sparse.dense_to_sparse for torch tensors")
    batch = np.asarray(batch)
    bhwc, _ = _as_bhwc(batch, channels_last)
    if mask is None:
        valid = np.any(bhwc != 0, axis=3)
    else:
        valid = np.asarray(mask, dtype=bool)
        check_shape(valid, "({}, {}, {})".format(*bhwc.shape[:3]), "mask")
    b, y, x = np.nonzero(valid)
    coords = np.stack([x, y, b], axis=1).astype(np.int64, copy=False)
    feats = np.ascontiguousarray(bhwc[b, y, x, :])
    return coords, feats


def sparse_to_dense(
    coords: np.ndarray,
    feats: np.ndarray,
    shape: tuple[int, ...],
    *,
    channels_last: bool = True,
) -> np.ndarray:
    """S2D: scatter a sparse tensor back into a zero-filled batch.

    Parameters
    ----------
    coords : (N, 3) integer array
        ``[x, y, b]`` per point, unique (as :func:`dense_to_sparse` produces them; with
        repeated coordinates which feature wins is unspecified).
    feats : (N, C) or (N,) array
        Features; the output has their dtype.
    shape : tuple
        Dense shape: ``(B, H, W, C)`` with ``channels_last=True`` (default), ``(B, C, H, W)``
        with ``channels_last=False``, or ``(B, H, W)`` for one channel.
    channels_last : bool
        Layout of a 4-D ``shape``.

    Returns
    -------
    batch : array of ``shape``
        Zeros except at ``coords``.

    Raises
    ------
    ParameterError
        Coordinates outside the batch, or features that do not match the channel count.
    """
    coords = np.asarray(coords)
    feats = np.asarray(feats)
    shape = tuple(int(s) for s in shape)
    check_shape(SimpleNamespace(shape=shape), "(B, H, W) | (B, H, W, C) | (B, C, H, W)", "shape")
    if len(shape) == 3:
        B, H, W = shape
        C = 1
    else:
        B, H, W, C = shape if channels_last else (shape[0], shape[2], shape[3], shape[1])
    check_values(shape, "shape", low=0)  # sizes
    n = check_shape(coords, "(N, 3)", "coords")["N"]  # [x, y, b]
    if coords.size:
        check_dtype(coords, "coords", "iu")
    if feats.ndim == 1:
        feats = feats[:, None]
    check_shape(feats, f"({n}, {C})", "feats")  # one row per coordinate, C channels
    out = np.zeros((B, H, W, C), dtype=feats.dtype)
    if coords.shape[0]:
        x, y, b = coords[:, 0], coords[:, 1], coords[:, 2]
        lo = coords.min(axis=0)
        hi = coords.max(axis=0)
        if lo.min() < 0 or hi[0] >= W or hi[1] >= H or hi[2] >= B:
            raise ParameterError(
                f"coords outside the batch: x in [{lo[0]}, {hi[0]}], y in [{lo[1]}, {hi[1]}], "
                f"b in [{lo[2]}, {hi[2]}] for B={B}, H={H}, W={W}"
            )
        out[b, y, x, :] = feats
    if len(shape) == 3:
        return out[..., 0]
    if not channels_last:
        return np.ascontiguousarray(np.moveaxis(out, 3, 1))
    return out
