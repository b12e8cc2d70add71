"""EffisDepth sparse tensors for torch: D2S and S2D on tensors (any device, autograd-safe).

Same conventions as the numpy versions in :mod:`sparsetools.ops.sparse`: coordinates
``[x, y, b]`` (int64), features ``(N, C)`` in the batch's dtype, a pixel is valid when any
channel is non-zero, and ``sparse_to_dense(*dense_to_sparse(x), x.shape) == x`` exactly.
Both functions return the same values as the numpy versions on the same data.
"""

from __future__ import annotations

import torch

from ..errors import ParameterError
from ..ops.sparse import infer_channels_last

__all__ = ["dense_to_sparse", "sparse_to_dense"]


def _as_bhwc(batch: torch.Tensor, channels_last: bool | None) -> torch.Tensor:
    if batch.dim() == 3:
        return batch.unsqueeze(-1)
    if batch.dim() != 4:
        raise ParameterError(
            f"expected a batch (B, H, W), (B, H, W, C) or (B, C, H, W), got shape "
            f"{tuple(batch.shape)}"
        )
    if infer_channels_last(tuple(batch.shape), channels_last):
        return batch
    return batch.permute(0, 2, 3, 1)


def dense_to_sparse(
    batch: torch.Tensor,
    *,
    channels_last: bool | None = None,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """D2S on a tensor.

    Parameters
    ----------
    batch : (B, H, W, C), (B, C, H, W) or (B, H, W) tensor
    channels_last : bool, optional
        Layout of a 4-D batch; inferred when unambiguous.
    mask : (B, H, W) bool tensor, optional
        Valid pixels; default: any channel non-zero (or NaN).

    Returns
    -------
    coords : (N, 3) int64 tensor, on ``batch.device``
        ``[x, y, b]`` in row-major order of ``(b, y, x)``.
    feats : (N, C) tensor
        Gathered from ``batch`` (gradients flow back to the gathered pixels).
    """
    if not isinstance(batch, torch.Tensor):
        raise ParameterError(
            f"expected a torch.Tensor, got {type(batch).__name__} "
            "(use sparsetools.ops.sparse.dense_to_sparse for numpy arrays)"
        )
    bhwc = _as_bhwc(batch, channels_last)
    if mask is None:
        valid = (bhwc != 0).any(dim=3)
    else:
        valid = torch.as_tensor(mask, device=bhwc.device).to(torch.bool)
        if tuple(valid.shape) != tuple(bhwc.shape[:3]):
            raise ParameterError(
                f"mask must have shape {tuple(bhwc.shape[:3])}, got {tuple(valid.shape)}"
            )
    b, y, x = torch.nonzero(valid, as_tuple=True)
    coords = torch.stack([x, y, b], dim=1).to(torch.int64)
    feats = bhwc[b, y, x, :]
    return coords, feats


def sparse_to_dense(
    coords: torch.Tensor,
    feats: torch.Tensor,
    shape: tuple[int, ...],
    *,
    channels_last: bool = True,
) -> torch.Tensor:
    """S2D on tensors: zeros of ``shape`` with ``feats`` scattered at ``coords``.

    Parameters
    ----------
    coords : (N, 3) integer tensor, ``[x, y, b]``, unique.
    feats : (N, C) or (N,) tensor; the output has its dtype and device.
    shape : ``(B, H, W, C)`` (``channels_last=True``), ``(B, C, H, W)`` or ``(B, H, W)``.

    Returns
    -------
    tensor of ``shape``
        Differentiable with respect to ``feats``.
    """
    if not isinstance(coords, torch.Tensor) or not isinstance(feats, torch.Tensor):
        raise ParameterError("coords and feats must be torch tensors")
    shape = tuple(int(s) for s in shape)
    if len(shape) == 3:
        B, H, W = shape
        C = 1
    elif len(shape) == 4:
        B, H, W, C = shape if channels_last else (shape[0], shape[2], shape[3], shape[1])
    else:
        raise ParameterError(f"shape must be (B, H, W) or 4-D, got {shape}")
    if coords.dim() != 2 or coords.shape[1] != 3:
        raise ParameterError(f"coords must be (N, 3) [x, y, b], got shape {tuple(coords.shape)}")
    if coords.dtype.is_floating_point or coords.dtype == torch.bool:
        raise ParameterError(f"coords must be integers, got {coords.dtype}")
    if feats.dim() == 1:
        feats = feats.unsqueeze(1)
    if feats.dim() != 2 or feats.shape[0] != coords.shape[0] or feats.shape[1] != C:
        raise ParameterError(
            f"feats must be ({coords.shape[0]}, {C}) to match coords and shape, "
            f"got {tuple(feats.shape)}"
        )
    out = feats.new_zeros((B, H, W, C))
    if coords.shape[0]:
        coords = coords.to(device=feats.device, dtype=torch.int64)
        lo = coords.min(dim=0).values.tolist()
        hi = coords.max(dim=0).values.tolist()
        if min(lo) < 0 or hi[0] >= W or hi[1] >= H or hi[2] >= B:
            raise ParameterError(
                f"coords outside the batch: x in [{lo[0]}, {hi[0]}], y in [{lo[1]}, {hi[1]}], "
                f"b in [{lo[2]}, {hi[2]}] for B={B}, H={H}, W={W}"
            )
        # index_put (not in-place on a leaf) keeps the result differentiable w.r.t. feats.
        out = out.index_put((coords[:, 2], coords[:, 1], coords[:, 0]), feats)
    if len(shape) == 3:
        return out[..., 0]
    if not channels_last:
        return out.permute(0, 3, 1, 2).contiguous()
    return out
