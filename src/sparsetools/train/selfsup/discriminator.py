"""RNW's Priors-Based Regularization (PBR), its network: a PatchGAN discriminator on
mean-normalised depth, its input and the LSGAN losses (the training step: :mod:`.pbr`).

The depth network is the generator of a least-squares GAN (LSGAN). Its discriminator sees
``cat(I_p, mu(D))``, where ``mu(D) = D / mean(D)`` removes the depth's scale and ``I_p`` is the
coordinate image (where in the picture each value lies: the road is near at the bottom, the
sky far at the top), and learns to tell the depth network's maps from unpaired reference
depths (:mod:`.pbr_reference`). Losses, as the DepthDark survey writes them (section 3)::

    L_D = 1/2 E_r[(Phi_D(cat(I_p, mu(D_r))) - 1)^2] + 1/2 E_t[Phi_D(cat(I_p, mu(D_t)))^2]
    L_G = 1/2 E_t[(Phi_D(cat(I_p, mu(D_t))) - 1)^2]

with the expectations taken as means over the batch and the output patches. The total loss of
the depth network gains ``xi * L_G``; the discriminator minimises ``tau * L_D`` with an
optimizer of its own (:class:`~.pbr.PriorsRegularizer`).

The discriminator works on a fixed grid of :data:`GRID` x :data:`GRID` cells: ``mu(D)`` is
box-averaged onto it (:func:`area_matrix`), whatever the size of the training images, so its
output is a 3 x 3 patch map for every training size (208x64, the toolkit's self-supervised
size, among them). Pixels without a reference depth are left out of both maps alike
(:func:`discriminator_input`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ...errors import ParameterError

__all__ = [
    "DISCRIMINATOR_SEED_OFFSET",
    "DISCRIMINATOR_WIDTH",
    "GRID",
    "LAYERS",
    "OUTPUT_SIZE",
    "PATCH_STRIDE",
    "RECEPTIVE_FIELD",
    "PatchDiscriminator",
    "area_matrix",
    "build_discriminator",
    "coordinate_image",
    "discriminator_input",
    "lsgan_discriminator_loss",
    "lsgan_generator_loss",
    "patch_geometry",
]

#: The discriminator's convolutions as (kernel, stride), no padding: 4x4 kernels (the survey's
#: "3x3 PatchGAN with 4x4 kernels").
LAYERS = ((4, 2), (4, 2), (4, 2), (4, 1))
#: Side of the square grid (cells) the discriminator sees. 62 is the size at which the three
#: output patches of a row tile it exactly: patch i sees cells 8i .. 8i + 45, 0..61 in all.
GRID = 62
#: Channels of the first convolution (doubled by each of the next two).
DISCRIMINATOR_WIDTH = 32
#: The discriminator's weights come from ``torch.initial_seed() + DISCRIMINATOR_SEED_OFFSET``
#: (a stream of its own: the depth and pose networks start alike with and without PBR).
DISCRIMINATOR_SEED_OFFSET = 7937


def patch_geometry(size: int, layers=LAYERS) -> tuple[int, int, int]:
    """Output side, receptive field and output stride of unpadded convolutions on ``size`` cells.

    Parameters
    ----------
    size : int
        Input side, cells.
    layers : sequence of (kernel, stride)

    Returns
    -------
    output, field, stride : int
        The output has ``output`` x ``output`` patches; patch ``i`` sees the input cells
        ``stride * i`` .. ``stride * i + field - 1`` (per axis).

    Notes
    -----
    Per layer of kernel k and stride s: ``n' = floor((n - k) / s) + 1``, the field grows by
    ``(k - 1)`` times the product of the earlier strides, the stride multiplies by s. For
    :data:`LAYERS` on 62 cells: 62 -> 30 -> 14 -> 6 -> 3 patches, field 4, 10, 22, 46 cells,
    stride 2, 4, 8, 8.
    """
    n, field, jump = int(size), 1, 1
    for k, s in layers:
        if n < k:
            raise ParameterError(f"a {size}-cell input is too small for the discriminator")
        n = (n - k) // s + 1
        field += (k - 1) * jump
        jump *= s
    return n, field, jump


OUTPUT_SIZE, RECEPTIVE_FIELD, PATCH_STRIDE = patch_geometry(GRID)


class PatchDiscriminator(nn.Module):
    """The PatchGAN discriminator of PBR: four 4x4 convolutions, 3 x 3 scores per map.

    Parameters
    ----------
    coordinates : bool
        Input ``cat(I_p, mu(D))`` (3 channels); False: ``mu(D)`` alone (1 channel).
    width : int
        Channels of the first layer (``width``, ``2 width``, ``4 width``, then 1).

    Notes
    -----
    Input (B, C, GRID, GRID), output (B, 1, 3, 3): :data:`LAYERS` without padding (a padded
    border would tell the patches apart by their edge, which the coordinate option is
    meant to control), LeakyReLU(0.2) between them, no normalisation layer (batch statistics
    would mix real and generated maps), no final activation (LSGAN scores). Each output patch
    sees :data:`RECEPTIVE_FIELD` = 46 x 46 grid cells at a stride of :data:`PATCH_STRIDE` = 8
    (:func:`patch_geometry`); on 208x64 training images a cell is 3.35 x 1.03 pixels, so a
    patch covers about 154 x 47 pixels of the image.
    """

    def __init__(self, *, coordinates: bool = True, width: int = DISCRIMINATOR_WIDTH):
        super().__init__()
        self.coordinates = bool(coordinates)
        self.width = int(width)
        channels = [3 if self.coordinates else 1, width, 2 * width, 4 * width, 1]
        layers: list[nn.Module] = []
        for i, (k, s) in enumerate(LAYERS):
            layers.append(nn.Conv2d(channels[i], channels[i + 1], k, stride=s))
            if i < len(LAYERS) - 1:
                layers.append(nn.LeakyReLU(0.2))
        self.net = nn.Sequential(*layers)

    @property
    def in_channels(self) -> int:
        return 3 if self.coordinates else 1

    def config(self) -> dict:
        """Constructor arguments and grid (a checkpoint's ``discriminator_config``)."""
        return {"coordinates": self.coordinates, "width": self.width, "grid": GRID}

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, GRID, GRID) -> (B, 1, 3, 3) scores (1 = reference, 0 = generated)."""
        if x.ndim != 4 or x.shape[1:] != (self.in_channels, GRID, GRID):
            raise ParameterError(
                f"the discriminator takes (B, {self.in_channels}, {GRID}, {GRID}), "
                f"got {tuple(x.shape)}"
            )
        return self.net(x)


def build_discriminator(config: dict) -> PatchDiscriminator:
    """The discriminator of a checked ``discriminator_config`` (weights from the current RNG)."""
    return PatchDiscriminator(coordinates=config["coordinates"], width=config["width"])


def area_matrix(n_in: int, n_out: int) -> torch.Tensor:
    """(n_out, n_in) float32 box-resampling weights along one axis.

    Output cell i spans ``[i n_in / n_out, (i + 1) n_in / n_out)`` input pixels; its weight on
    pixel j is the length of their overlap over the cell's length, so every row sums to 1 and a
    constant stays constant, downsampling (averages) and upsampling (copies) alike. As a
    matrix product the resampling is deterministic on every device (torch's adaptive pooling
    has no deterministic CUDA backward).
    """
    edges = np.arange(n_out + 1, dtype=np.float64) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    j = np.arange(n_in, dtype=np.float64)[None, :]
    overlap = np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)
    return torch.from_numpy((overlap / (n_in / n_out)).astype(np.float32))


def coordinate_image(batch: int, *, device=None) -> torch.Tensor:
    """I_p: (batch, 2, GRID, GRID) float32, the row and column of each grid cell's centre as a
    fraction of the image's height and width (0 = top / left, 1 = bottom / right)."""
    centres = (torch.arange(GRID, dtype=torch.float32, device=device) + 0.5) / GRID
    rows = centres.view(1, 1, GRID, 1).expand(batch, 1, GRID, GRID)
    cols = centres.view(1, 1, 1, GRID).expand(batch, 1, GRID, GRID)
    return torch.cat([rows, cols], dim=1)


def discriminator_input(
    depth: torch.Tensor, valid: torch.Tensor, *, coordinates: bool
) -> torch.Tensor:
    """What the discriminator sees of a batch of depth maps: ``cat(I_p, mu(D))`` on the grid.

    Parameters
    ----------
    depth : (B, 1, H, W) float, metres
        Predicted or reference depth (differentiable: the generator's gradient flows back).
    valid : (B, 1, H, W) bool
        Pixels that count: where the reference depth of the same batch position is known
        (a generated map is masked with the reference it is paired with, so the two kinds of
        input have the same holes and the holes tell the discriminator nothing).
    coordinates : bool
        Prepend the coordinate image I_p (:func:`coordinate_image`).

    Returns
    -------
    (B, 3 or 1, GRID, GRID) float32
        ``mu(D) = D / mean(D)`` (mean over the valid pixels of each map), box-averaged over
        the valid pixels of each cell (:func:`area_matrix`); 0 in a cell without any.
    """
    if depth.ndim != 4 or depth.shape[1] != 1 or valid.shape != depth.shape:
        raise ParameterError(
            f"depth and valid must be (B, 1, H, W) alike, got {tuple(depth.shape)} and "
            f"{tuple(valid.shape)}"
        )
    b, _, h, w = depth.shape
    m = valid.to(depth.dtype)
    count = m.sum(dim=(2, 3), keepdim=True)
    mean = (depth * m).sum(dim=(2, 3), keepdim=True) / count.clamp_min(1.0)
    normalised = depth / torch.where(mean > 0, mean, torch.ones_like(mean))
    rows = area_matrix(h, GRID).to(depth.device, depth.dtype)
    cols = area_matrix(w, GRID).to(depth.device, depth.dtype)
    weight = rows @ m @ cols.T
    total = rows @ (normalised * m) @ cols.T
    grid = torch.where(weight > 0, total / weight.clamp_min(1e-12), torch.zeros_like(total))
    if not coordinates:
        return grid
    return torch.cat([coordinate_image(b, device=depth.device).to(grid.dtype), grid], dim=1)


def lsgan_discriminator_loss(real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """L_D = 1/2 mean((real - 1)^2) + 1/2 mean(fake^2) over the batch and the patches.

    Parameters
    ----------
    real, fake : (B, 1, 3, 3) float
        Discriminator scores of reference and generated maps (``fake`` detached from the
        depth network when the discriminator is trained).
    """
    return 0.5 * ((real - 1.0) ** 2).mean() + 0.5 * (fake**2).mean()


def lsgan_generator_loss(fake: torch.Tensor) -> torch.Tensor:
    """L_G = 1/2 mean((fake - 1)^2): the depth network wants its maps scored as references."""
    return 0.5 * ((fake - 1.0) ** 2).mean()
