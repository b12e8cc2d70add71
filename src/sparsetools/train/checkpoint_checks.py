"""Checks of an untrusted checkpoint's content, before anything is built from it.

:func:`sparsetools.train.checkpoint.load_checkpoint` runs them in order: the file is torch's
zip format and loads with ``weights_only=True`` (torch's own warnings silenced: the error says
what is wrong); the model configuration has the right types and a bounded size
(:data:`~sparsetools.train.config.MAX_WIDTH`); the weights have the names and shapes of the
network that configuration builds (built on torch's ``meta`` device: no memory); the training
configuration agrees with the networks (``--resume`` rebuilds them from it); the optimizer, RNG
and SBM entries have the structure training restores; PBR's discriminator (when present) has a
known configuration, fitting weights and an optimizer state; a URL model's reading of its head
(``url``, the gate) goes with its input mode. Each failure is one
:class:`~sparsetools.errors.FormatError` naming the file.
"""

from __future__ import annotations

import math
import re
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import torch

from ..errors import FormatError, ParameterError
from .config import MAX_WIDTH, TrainConfig
from .model import INPUT_CHANNELS, LIDAR_ENCODERS, LIDAR_SCALES, OUTPUTS, check_lidar_scales
from .url import URL_MODES, URL_VARIANTS

#: A run id: 32 hex digits (``uuid4().hex``).
RUN_ID = re.compile(r"[0-9a-f]{32}")

__all__ = [
    "CHECKPOINT_FORMAT",
    "RUN_ID",
    "check_agreement",
    "check_discriminator",
    "check_extras",
    "check_model_config",
    "check_pose_config",
    "check_weights",
    "load_weights",
    "read_checkpoint_file",
]

CHECKPOINT_FORMAT = "sparsetools-depth-checkpoint"


def read_checkpoint_file(
    path: Path, *, expected: str = CHECKPOINT_FORMAT, what: str = "sparsetools depth checkpoint"
) -> dict:
    """The checkpoint's top-level dict: torch's zip format only, read with weights_only, whose
    ``format`` tag is ``expected`` (else "not a ``what``"; the densifier of
    :mod:`.densifier` has its own tag)."""
    try:
        is_zip = zipfile.is_zipfile(path)
    except OSError as exc:
        raise FormatError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    if not is_zip:
        raise FormatError(
            f"{path}: not a readable torch checkpoint (not torch's zip format: a legacy "
            "pickle file or another kind of file)"
        )
    try:
        # torch warns about pickle protocols and legacy features of such files: the error
        # below says what is wrong, on one line
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types (pickle, zip, runtime) for bad files
        raise FormatError(
            f"{path}: not a readable torch checkpoint ({type(exc).__name__})"
        ) from exc
    if not isinstance(raw, dict) or raw.get("format") != expected:
        raise FormatError(f"{path}: not a {what}")
    return raw


def _is_int(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_width(value, path: Path, what: str) -> None:
    if not _is_int(value) or not 1 <= value <= MAX_WIDTH:
        shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:37] + "..."
        raise FormatError(
            f"{path}: {what} width must be an integer from 1 to {MAX_WIDTH}, got {shown}"
        )


def check_model_config(mc, path: Path) -> dict:
    """The depth network's constructor arguments, type- and size-checked before any build."""
    if not isinstance(mc, dict):
        raise FormatError(f"{path}: model_config must be a mapping, got {type(mc).__name__}")
    mode = mc.get("input_mode")
    if not isinstance(mode, str) or mode not in INPUT_CHANNELS:
        raise FormatError(
            f"{path}: unknown input mode {mode!r} in model_config "
            f"(known: {', '.join(sorted(INPUT_CHANNELS))})"
        )
    _check_width(mc.get("width"), path, "model_config")
    if not isinstance(mc.get("final_layer"), bool):
        raise FormatError(f"{path}: model_config final_layer must be true or false")
    if mc.get("output", "depth") not in OUTPUTS:
        raise FormatError(f"{path}: unknown output {mc.get('output')!r} in model_config")
    if mc.get("lidar_encoder", "none") not in LIDAR_ENCODERS:
        raise FormatError(
            f"{path}: unknown LiDAR encoder {mc.get('lidar_encoder')!r} in model_config"
        )
    if "depth_range" in mc:
        lo_hi = mc["depth_range"]
        if not (
            isinstance(lo_hi, (list, tuple))
            and len(lo_hi) == 2
            and all(map(_is_number, lo_hi))
            and 0 < lo_hi[0] < lo_hi[1] < math.inf
        ):
            raise FormatError(f"{path}: model_config depth_range must be 0 < min < max < inf")
    depth = mc.get("initial_depth")
    if depth is not None and not (_is_number(depth) and 0 < depth < math.inf):
        raise FormatError(f"{path}: model_config initial_depth must be a positive number")
    try:  # before 0.4 every level was fed, and checkpoints did not say so
        check_lidar_scales(mc.get("lidar_scales", list(LIDAR_SCALES)))
    except ParameterError as exc:
        raise FormatError(f"{path}: model_config {exc}") from None
    url = mc.get("url")
    if (url is not None and url not in URL_VARIANTS) or (mode in URL_MODES) != (url is not None):
        raise FormatError(f"{path}: model_config url {url!r} does not go with input mode {mode!r}")
    alpha, beta = mc.get("gate_alpha"), mc.get("gate_beta")
    if url is not None and not (
        _is_number(alpha) and 0 < alpha < math.inf and _is_number(beta) and math.isfinite(beta)
    ):
        raise FormatError(f"{path}: model_config needs gate_alpha > 0 and a finite gate_beta")
    return dict(mc)


def check_pose_config(pc, path: Path) -> dict:
    if not isinstance(pc, dict):
        raise FormatError(f"{path}: pose_config must be a mapping, got {type(pc).__name__}")
    _check_width(pc.get("width"), path, "pose_config")
    if pc.get("lidar_encoder", "none") not in LIDAR_ENCODERS:
        raise FormatError(
            f"{path}: unknown LiDAR encoder {pc.get('lidar_encoder')!r} in pose_config"
        )
    scale = pc.get("translation_scale", 0.01)
    if not (_is_number(scale) and 0 < scale < math.inf):
        raise FormatError(f"{path}: pose_config translation_scale must be a positive number")
    return dict(pc)


def check_weights(weights, build: Callable, path: Path, what: str) -> dict:
    """Weights whose names and shapes are those of the network ``build()`` makes.

    The network is built on torch's ``meta`` device: its tensors have shapes but no storage,
    so checking a (bounded) configuration costs no memory.
    """
    if not isinstance(weights, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in weights.items()
    ):
        raise FormatError(f"{path}: the {what} weights are not a mapping of names to tensors")
    with torch.device("meta"):
        expected = {k: tuple(v.shape) for k, v in build().state_dict().items()}
    got = {k: tuple(v.shape) for k, v in weights.items()}
    if got != expected:
        missing = sorted(set(expected) - set(got))
        extra = sorted(set(got) - set(expected))
        if missing:
            detail = f"no '{missing[0]}'"
        elif extra:
            detail = f"unexpected '{extra[0]}'"
        else:
            name = next(k for k in expected if got[k] != expected[k])
            detail = f"'{name}' is {got[name]}, the configuration gives {expected[name]}"
        raise FormatError(f"{path}: {what} weights do not fit its configuration ({detail})")
    return weights


def check_discriminator(raw: dict, path: Path) -> dict | None:
    """PBR's discriminator entries of a self-supervised checkpoint, checked: its configuration
    (None when the checkpoint has none: a run without PBR)."""
    from .selfsup.discriminator import DISCRIMINATOR_WIDTH, GRID, build_discriminator

    if raw.get("discriminator_config") is None and raw.get("discriminator") is None:
        return None
    dc = raw.get("discriminator_config")
    if not (
        isinstance(dc, dict)
        and isinstance(dc.get("coordinates"), bool)
        and dc.get("width") == DISCRIMINATOR_WIDTH
        and dc.get("grid") == GRID
    ):
        raise FormatError(
            f"{path}: discriminator_config must say coordinates (true or false), width "
            f"{DISCRIMINATOR_WIDTH} and grid {GRID}"
        )
    check_weights(raw.get("discriminator"), lambda: build_discriminator(dc), path, "discriminator")
    if not isinstance(raw.get("discriminator_optimizer"), dict):
        raise FormatError(f"{path}: no optimizer state of the PBR discriminator")
    _check_optimizer(raw["discriminator_optimizer"], path, "the discriminator's optimizer")
    return dict(dc)


def check_agreement(
    config: TrainConfig,
    mc: dict,
    pc: dict | None,
    kind: str,
    path: Path,
    *,
    discriminator: dict | None = None,
) -> None:
    """The training configuration must describe the networks stored beside it (``--resume``
    rebuilds them from it)."""
    pairs = [
        ("input_mode", config.input_mode, mc["input_mode"]),
        ("width", config.width, mc["width"]),
        ("lidar_encoder", config.lidar_encoder, mc.get("lidar_encoder", "none")),
        (
            "lidar_scales",
            tuple(config.lidar_scales) if config.lidar_encoder != "none" else None,
            tuple(mc.get("lidar_scales", LIDAR_SCALES)) if "lidar_encoder" in mc else None,
        ),
        ("self_supervised", config.self_supervised, kind == "self-supervised"),
        ("url", config.url, mc.get("url")),
    ]
    if mc.get("url") is not None:
        pairs.append(("gate_alpha", config.gate_alpha, mc["gate_alpha"]))
        pairs.append(("gate_beta", config.gate_beta, mc["gate_beta"]))
    if mc.get("output", "depth") == "depth":
        pairs.append(("final_layer", config.final_layer, mc["final_layer"]))
    if config.selfsup is not None and pc is not None:
        pairs.append(("pose_width", config.selfsup.pose_width, pc["width"]))
        pairs.append(
            (
                "pose_lidar_encoder",
                config.selfsup.pose_lidar_encoder,
                pc.get("lidar_encoder", "none"),
            )
        )
    if config.selfsup is not None:
        pbr = config.selfsup.pbr is not None
        if pbr != (discriminator is not None):
            raise FormatError(
                f"{path}: its training configuration {'has' if pbr else 'has no'} --pbr, but "
                f"the checkpoint {'lacks' if pbr else 'holds'} a PBR discriminator"
            )
        if pbr:
            pairs.append(
                ("pbr_coordinates", config.selfsup.pbr_coordinates, discriminator["coordinates"])
            )
    for name, theirs, mine in pairs:
        if theirs != mine:
            raise FormatError(
                f"{path}: its training configuration says {name} {theirs!r}, its networks {mine!r}"
            )


def _check_optimizer(opt, path: Path, what: str) -> None:
    if opt is not None and not (
        isinstance(opt, dict)
        and isinstance(opt.get("state", {}), dict)
        and isinstance(opt.get("param_groups", []), list)
        and all(
            isinstance(g, dict) and isinstance(g.get("params"), list)
            for g in opt.get("param_groups", [])
        )
    ):
        raise FormatError(f"{path}: {what} state is not torch's optimizer state dict")


def check_extras(raw: dict, path: Path) -> None:
    """Optimizer, RNG and SBM entries of the structure training restores."""
    _check_optimizer(raw.get("optimizer"), path, "the optimizer")
    rng = raw.get("rng")
    state = rng.get("torch") if isinstance(rng, dict) else None
    reference = torch.get_rng_state()
    if not (
        isinstance(state, torch.Tensor)
        and state.dtype == reference.dtype
        and state.shape == reference.shape
    ):
        raise FormatError(f"{path}: incomplete checkpoint (no valid torch RNG state)")
    sbm = raw.get("sbm_threshold")
    if sbm is not None and not (_is_number(sbm) and math.isfinite(sbm)):
        raise FormatError(f"{path}: sbm_threshold must be a finite number")


def load_weights(module: torch.nn.Module, weights: dict, path: Path, what: str) -> None:
    """Load a state dict; a mismatch is a one-line :class:`FormatError` naming ``path``."""
    try:
        module.load_state_dict(weights)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = first[1].strip() if len(first) > 1 else first[0]
        raise FormatError(f"{path}: {what} weights do not fit the model ({detail})") from exc
