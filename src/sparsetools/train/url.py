"""URL, the second stage of the all-day depth completion (DepthDark survey, section 6).

The first stage, the learned densifier (:mod:`.densifier`, SpaDe-style), turns the sparse map
``S`` of a sample into a coarse dense depth ``D_c`` and a log-variance ``U = log sigma^2``
(sigma in metres). URL refines it with the camera image ``I``. ``train --input rgbdu`` feeds
the early-fusion U-Net (:mod:`.model`) with ``I``, ``D_c`` and ``U`` and reads its head in one of
two ways (``--url``):

- ``residual``: ``D_f = D_c + R(I, U)``; the head is the residual ``R`` in metres (linear,
  signed, starting at exactly 0: an untrained model returns ``D_c``);
- ``gated``: the head is the model's own depth ``P`` (the usual softplus head) and the output is
  ``lambda(U) D_c + (1 - lambda(U)) P`` with URL's fixed gate
  ``lambda(U) = 1 / (1 + exp(alpha (U - beta)))``
  (:func:`sparsetools.ops.uncertainty.uncertainty_gate`; alpha 0.8 and beta 0 by default,
  ``--gate-alpha`` / ``--gate-beta``): where the densifier is sure (low ``U``) its depth is
  kept, where it is not the network's prediction takes over.

``D_c`` and ``U`` are computed when a sample is loaded, from the sparse map the network is
shown (after the augmentation), by :class:`~.densifier.LearnedDensifier` under
``torch.inference_mode`` (no gradient reaches the densifier: it stays as trained). Not
precomputed: neither IP-Basic's fill nor the densifier is equivariant to the flip, the crop or
the scale of the augmentation, so maps of the whole frames could not follow it exactly, and no
stored map can go stale when ``densifier.pt`` is retrained. A pure function of the map, so
training stays bit-identical for a seed and resumes exactly. A run keeps the densifier's weights in every checkpoint, so ``eval`` and ``predict`` compute the same
inputs without the densifier file, and ``--resume`` continues with the very densifier the run
started with.
"""

from __future__ import annotations

import torch

from ..errors import ParameterError
from ..ops.uncertainty import GATE_ALPHA, GATE_BETA
from ..validate import check_finite, check_positive

__all__ = [
    "GATE_ALPHA",
    "GATE_BETA",
    "URL_MODES",
    "URL_VARIANTS",
    "check_url_settings",
    "gated_fusion",
    "uncertainty_gate",
]

#: Input modes that feed the densifier's ``D_c`` and ``U`` (rgb + D_c + U: 5 channels).
URL_MODES = ("rgbdu",)
#: How the network's head is read in a URL mode (module docstring).
URL_VARIANTS = ("residual", "gated")


def uncertainty_gate(log_var: torch.Tensor, *, alpha: float, beta: float) -> torch.Tensor:
    """URL's gate ``lambda(U) = 1 / (1 + exp(alpha (U - beta)))`` on a tensor.

    Parameters
    ----------
    log_var : (...) float tensor, log of square metres
        ``U = log sigma^2``.
    alpha : float, 1 / log of square metres
        Steepness (> 0).
    beta : float, log of square metres
        Where the gate is 0.5.

    Returns
    -------
    (...) tensor in [0, 1]: the weight of ``D_c``. ``sigmoid(-alpha (U - beta))``, the formula
    without overflow (the torch twin of :func:`sparsetools.ops.uncertainty.uncertainty_gate`).
    """
    return torch.sigmoid(-alpha * (log_var - beta))


def gated_fusion(
    coarse: torch.Tensor,
    prediction: torch.Tensor,
    log_var: torch.Tensor,
    *,
    alpha: float = GATE_ALPHA,
    beta: float = GATE_BETA,
) -> torch.Tensor:
    """``lambda(U) D_c + (1 - lambda(U)) P``.

    Parameters
    ----------
    coarse : (B, 1, H, W) float tensor, metres
        The densifier's ``D_c``.
    prediction : (B, 1, H, W) float tensor, metres
        The network's own depth ``P``.
    log_var : (B, 1, H, W) float tensor, log of square metres
        ``U`` of ``coarse``.
    alpha, beta : float
        The gate's parameters (:func:`uncertainty_gate`).

    Returns
    -------
    (B, 1, H, W) float tensor, metres
    """
    lam = uncertainty_gate(log_var, alpha=alpha, beta=beta)
    return lam * coarse + (1 - lam) * prediction


def check_url_settings(config) -> None:
    """Refuse URL settings that are inconsistent (one line naming the option).

    Parameters
    ----------
    config : TrainConfig
        Its ``input_mode``, ``url``, ``densifier``, ``gate_alpha``, ``gate_beta``,
        ``final_layer`` and ``selfsup``.

    Raises
    ------
    ParameterError
        A URL option without ``--input rgbdu`` (or gate options without ``--url gated``), the
        mode without ``--url`` or ``--densifier``, an unknown variant, a gate parameter out of
        range, the mode with ``--final-layer`` or ``--self-supervised``.
    """
    url, mode = config.url, config.input_mode
    alpha = check_positive(config.gate_alpha, "gate_alpha")
    beta = check_finite(config.gate_beta, "gate_beta")
    gate_set = [
        name
        for name, value, default in (
            ("--gate-alpha", alpha, GATE_ALPHA),
            ("--gate-beta", beta, GATE_BETA),
        )
        if value != default
    ]
    if mode not in URL_MODES:
        given = [o for o, v in (("--url", url), ("--densifier", config.densifier)) if v is not None]
        if given + gate_set:
            first = (given + gate_set)[0]
            raise ParameterError(
                f"{first} is a setting of URL, which refines the learned densifier's D_c "
                "and U: add --input rgbdu",
                param=first,
            )
        return
    if url not in URL_VARIANTS:
        raise ParameterError(
            f"--url must be {' or '.join(URL_VARIANTS)} with --input {mode}, got {url!r}",
            param="--url",
        )
    if config.densifier is None or not str(config.densifier).strip():
        raise ParameterError(
            f"--densifier CHECKPOINT is missing: --input {mode} feeds the learned densifier's "
            "D_c and U (densifier.pt of train-densifier, or its run folder)",
            param="--densifier",
        )
    if url != "gated" and gate_set:
        raise ParameterError(
            f"{gate_set[0]} is a setting of --url gated, not --url {url}", param=gate_set[0]
        )
    if config.final_layer:
        raise ParameterError(
            f"--final-layer does not go with --input {mode}: URL already refines the "
            f"densifier's D_c (--url {url})",
            param="--final-layer",
        )
    if config.selfsup is not None:
        raise ParameterError(
            f"--input {mode} (URL) is supervised depth completion: not available with "
            "--self-supervised",
            param="--input",
        )
