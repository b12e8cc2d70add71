"""The self-supervised loss of a batch of triplets (monodepth2 + EffisDepth + RNW).

At each scale s of the depth network (s = 0..scales-1):

1. the disparity is upsampled (bilinear) to the input resolution and read as depth
   (:func:`~sparsetools.train.model.disparity_to_depth`);
2. each source frame (t-1, t+1) is warped into the target view
   (:func:`~.geometry.warp_frame`) and compared with the target, pe(I_t, I_s->t)
   (:func:`~.photometric.photometric_error`); a pixel that projects behind a source camera
   gets no error from that source;
3. per pixel the minimum over the sources is kept (minimum reprojection); the pixel counts
   when the auto-mask, the SBM (of the source that gave the minimum) and "some source in
   front" all say so; the photometric term is the mean over ALL pixels of the masked minimum
   (masked pixels add 0), which is monodepth2's value for the gradient;
4. edge-aware smoothness of the scale's own disparity against the target resized to it
   (area interpolation), weight ``smoothness / 2^s``;
5. the sparse loss (L1 in metres, or SILog with ``silog_lambda``) of the upsampled depth on
   the pixels with valid sparse depth, weight ``sparse_weight``.

The total is the mean over the scales. :class:`LossTerms` also carries, at scale 0, the
photometric loss as monodepth2 reports it -- per pixel the minimum over the warped AND (with
the auto-mask) the unwarped sources, averaged over all pixels, so it starts at the identity
error and falls as the warp explains more -- and the plain minimum reprojection error (warped
sources only), which rises above the identity error wherever the warp does not fit (sky,
moving objects) and is a diagnostic only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..config import SelfSupSettings
from ..losses import l1_loss, silog_loss
from ..model import disparity_to_depth
from .geometry import warp_frame
from .masks import StatisticsMask, auto_mask, temporal_change
from .photometric import photometric_error
from .smoothness import edge_aware_smoothness

__all__ = ["LossTerms", "selfsup_loss"]

#: Error given to a source a pixel projects behind (loses every minimum; never a gradient).
_BEHIND = 1e3


@dataclass(frozen=True)
class LossTerms:
    """The loss of a batch and its parts (floats are batch means, detached).

    total : () tensor, the loss to minimise
    photometric : monodepth2's photometric loss at scale 0 (see the module docstring)
    reprojection : plain minimum reprojection error at scale 0 (warped sources only)
    masked_photometric : the photometric term that is minimised, mean over scales
    smoothness : unweighted edge-aware smoothness, mean over scales
    sparse : unweighted sparse loss, mean over scales (0 when there is none)
    mask_fraction : fraction of pixels the photometric term uses at scale 0
    """

    total: torch.Tensor
    photometric: float
    reprojection: float
    masked_photometric: float
    smoothness: float
    sparse: float
    mask_fraction: float

    def as_row(self) -> dict[str, float]:
        """Per-batch numbers for the training log (``loss`` = total)."""
        return {
            "loss": float(self.total.detach()),
            "photometric": self.photometric,
            "reprojection": self.reprojection,
            "masked_photometric": self.masked_photometric,
            "smoothness": self.smoothness,
            "sparse": self.sparse,
            "mask_fraction": self.mask_fraction,
        }


def selfsup_loss(
    disparities: list[torch.Tensor],
    frames: torch.Tensor,
    K: torch.Tensor,
    transforms: tuple[torch.Tensor, torch.Tensor],
    settings: SelfSupSettings,
    *,
    sparse: torch.Tensor | None = None,
    sbm: StatisticsMask | None = None,
    update_sbm: bool = False,
    generator: torch.Generator | None = None,
) -> LossTerms:
    """Loss of a batch of triplets.

    Parameters
    ----------
    disparities : list of (B, 1, h_s, w_s) float
        Sigmoid outputs of the depth network, finest first (at least ``settings.scales``).
    frames : (B, 3, 3, H, W) float, 0..1
        [previous, target, following] as the photometric loss compares them.
    K : (B, 3, 3) float
    transforms : (T_t_to_prev, T_t_to_next), each (B, 4, 4)
    settings : SelfSupSettings
    sparse : (B, 1, H, W) float, metres, optional
        Sparse depth of the target (0 = none), for the sparse loss.
    sbm : StatisticsMask, optional
        RNW's mask with its running threshold (``settings.sbm``).
    update_sbm : bool
        Fold this batch into the SBM threshold first (training batches only).
    generator : torch.Generator, optional
        Noise of the auto-mask's tie breaking.

    Returns
    -------
    LossTerms
    """
    target = frames[:, 1]
    sources = frames[:, [0, 2]]
    h, w = target.shape[-2:]
    identity = torch.cat([photometric_error(sources[:, i], target) for i in range(2)], dim=1)
    sbm_mask = None
    if sbm is not None:
        change = temporal_change(target, sources)
        if update_sbm:
            sbm.update(change)
        sbm_mask = sbm.mask(change)

    totals, masked_pe, smooth, sparse_terms = [], [], [], []
    monodepth2_pe, plain_pe, fraction = 0.0, 0.0, 0.0
    best_identity = identity.detach().min(dim=1, keepdim=True).values
    lo, hi = settings.depth_range
    for s in range(settings.scales):
        disp = disparities[s]
        full = (
            disp
            if s == 0
            else F.interpolate(disp, size=(h, w), mode="bilinear", align_corners=False)
        )
        depth = disparity_to_depth(full, lo, hi)
        errors, fronts = [], []
        for i, T in enumerate(transforms):
            warp = warp_frame(sources[:, i], depth, T, K)
            pe = photometric_error(warp.image, target)
            errors.append(torch.where(warp.in_front, pe, torch.full_like(pe, _BEHIND)))
            fronts.append(warp.in_front)
        reprojection = torch.cat(errors, dim=1)
        best, chosen = reprojection.min(dim=1, keepdim=True)
        use = fronts[0] | fronts[1]
        if settings.auto_mask:
            use = use & auto_mask(reprojection, identity, generator=generator)
        if sbm_mask is not None:
            use = use & torch.gather(sbm_mask, 1, chosen)
        term = (best * use).sum() / best.numel()
        total = term
        if s == 0:
            seen = fronts[0] | fronts[1]
            best0 = best.detach()
            plain_pe = float((best0 * seen).sum() / seen.sum().clamp(min=1))
            if settings.auto_mask:
                monodepth2_pe = float(torch.minimum(best0, best_identity).mean())
            else:
                monodepth2_pe = plain_pe
            fraction = float(use.float().mean())
        image_s = target if s == 0 else F.interpolate(target, size=disp.shape[-2:], mode="area")
        sm = edge_aware_smoothness(disp, image_s)
        total = total + settings.smoothness / 2**s * sm
        if sparse is not None and settings.sparse_loss != "none":
            if settings.sparse_loss == "l1":
                sp = l1_loss(depth, sparse)
            else:
                sp = silog_loss(depth, sparse, lam=settings.silog_lambda)
            total = total + settings.sparse_weight * sp
            sparse_terms.append(float(sp.detach()))
        totals.append(total)
        masked_pe.append(float(term.detach()))
        smooth.append(float(sm.detach()))
    n = len(totals)
    return LossTerms(
        total=torch.stack(totals).mean(),
        photometric=monodepth2_pe,
        reprojection=plain_pe,
        masked_photometric=sum(masked_pe) / n,
        smoothness=sum(smooth) / n,
        sparse=sum(sparse_terms) / n if sparse_terms else 0.0,
        mask_fraction=fraction,
    )
