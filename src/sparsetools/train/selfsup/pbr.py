"""RNW's Priors-Based Regularization (PBR), its training step: the discriminator of
:mod:`.discriminator` trained alternately with the depth network (:class:`PriorsRegularizer`)."""

from __future__ import annotations

import math

import torch

from ...errors import ParameterError
from .discriminator import (
    DISCRIMINATOR_SEED_OFFSET,
    PatchDiscriminator,
    discriminator_input,
    lsgan_discriminator_loss,
    lsgan_generator_loss,
)

__all__ = ["PriorsRegularizer"]


def _finite_or_raise(value: torch.Tensor, what: str, step: int) -> None:
    """Refuse a non-finite discriminator loss like the training loop refuses a diverged one."""
    if not math.isfinite(float(value.detach())):
        raise ParameterError(
            f"training diverged: the {what} is {float(value.detach())} at step {step + 1}; "
            "lower --lr or --pbr-discriminator-weight",
            param="lr",
        )


class PriorsRegularizer:
    """PBR in a self-supervised run: the discriminator, its optimizer and the reference draws.

    Parameters
    ----------
    config : TrainConfig
        With ``selfsup.pbr`` set.
    reference : ReferenceDepths
        The reference depths (:class:`~sparsetools.train.selfsup.pbr_reference.ReferenceDepths`).
    device : torch.device

    Notes
    -----
    Alternating updates, the generator first (as pix2pix-style GAN training does): in
    training step k, :meth:`generator_loss` scores the depth network's map with the
    discriminator frozen, and the epoch loop adds ``xi * L_G`` to the depth network's loss
    and takes its optimizer step; then :meth:`update_discriminator` takes one step of the
    discriminator's own optimizer (``config.optimizer`` at the epoch's learning rate,
    :func:`sparsetools.train.config.epoch_lr`) on ``tau * L_D``, the generated maps of step k
    detached. ``tau`` is the weight of L_D in the survey's total loss; since L_D reaches only
    the discriminator's weights, it acts as a factor on the discriminator's gradient: its
    learning rate with SGD, hardly anything with Adam (whose steps do not depend on a
    constant factor on the loss, up to its epsilon 1e-8).
    """

    def __init__(self, config, *, reference, device: torch.device):
        from ..epochs import make_optimizer

        settings = config.selfsup
        self.coordinates = bool(settings.pbr_coordinates)
        self.discriminator_weight = float(settings.pbr_discriminator_weight)
        self.reference = reference
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(torch.initial_seed() + DISCRIMINATOR_SEED_OFFSET)
            self.discriminator = PatchDiscriminator(coordinates=self.coordinates).to(device)
        self.optimizer = make_optimizer(self.discriminator.parameters(), config)
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None

    def generator_loss(self, depth: torch.Tensor, *, step: int) -> torch.Tensor:
        """L_G of a batch of predicted depth maps (gradient to the depth network only).

        Parameters
        ----------
        depth : (B, 1, H, W) float, metres
            The depth network's full-resolution depth (scale 0).
        step : int
            Optimizer steps done before (draws the step's reference maps).
        """
        reference = self.reference.draw(step=step, batch=depth.shape[0]).to(depth.device)
        valid = reference > 0
        real = discriminator_input(reference, valid, coordinates=self.coordinates)
        fake = discriminator_input(depth, valid, coordinates=self.coordinates)
        # frozen for this forward pass only: the loss's graph holds no discriminator weight
        self.discriminator.requires_grad_(False)
        try:
            score = self.discriminator(fake)
        finally:
            self.discriminator.requires_grad_(True)
        self._pending = (real, fake.detach())
        return lsgan_generator_loss(score)

    def update_discriminator(self, *, lr: float, step: int) -> dict[str, float]:
        """One step of the discriminator on the maps of the last :meth:`generator_loss`.

        Returns
        -------
        dict
            ``pbr_discriminator`` (L_D), ``pbr_real`` and ``pbr_fake`` (mean scores of the
            reference and generated maps before the step).
        """
        if self._pending is None:
            raise RuntimeError("update_discriminator before generator_loss")
        real, fake = self._pending
        self._pending = None
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        real_score, fake_score = self.discriminator(real), self.discriminator(fake)
        loss = lsgan_discriminator_loss(real_score, fake_score)
        _finite_or_raise(loss, "discriminator loss (--pbr)", step)
        self.optimizer.zero_grad(set_to_none=True)
        (self.discriminator_weight * loss).backward()
        self.optimizer.step()
        return {
            "pbr_discriminator": float(loss.detach()),
            "pbr_real": float(real_score.detach().mean()),
            "pbr_fake": float(fake_score.detach().mean()),
        }
