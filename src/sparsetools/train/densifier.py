"""A learned sparse-to-dense densifier with uncertainty (SpaDe, DepthDark survey section 6).

SpaDe maps a sparse projected LiDAR map ``S`` to a coarse dense depth and a log-variance::

    D_c = f_theta(S),    U = g_theta(S)     (U = log sigma^2, sigma in metres)

and is trained on synthetic data from exact ground truth (:mod:`.densifier_train`). This
module holds the network, its loss, its checkpoint and the picklable predictor that
``densify --method learned`` runs.

**Network** (:class:`SparseDensifier`, 0.15 M parameters at width 8; SpaDe has about 3 M):
sized for one CPU thread (a 1242x375 frame in 0.22 s, docs/densify.md). ``D_c`` is a learned
correction of a classical fill, so a short training on a CPU starts from a sound map and
spends itself on the corrections and on ``U``:

1. **Base** ``B``: IP-Basic's fill of ``S`` (:func:`classical_base`, the paper's version,
   OpenCV, about 11 ms per frame) where it gives a value; elsewhere (holes wider than its
   kernels, a map with few beams) a parameter-free push-pull fill (Gortler et al. 1996,
   :func:`push_pull`): *pull* keeps the nearest measurement (smallest depth) of each 2x2
   block, level after level, until one pixel is left; *push* walks back, each pixel keeping
   its level's value where its block holds a measurement and taking the bilinear upsampling
   of the coarser level (in ``log`` depth) where it does not. ``k`` counts the levels a pixel
   had to go up (0 where measured, about ``log2`` of the distance to the nearest measurement).
   A map with no measurement gets ``B = reference_depth`` everywhere.
2. Five input channels at full resolution: the mask ``M = [S > 0]``, ``M (log S - log B)``
   (how a measurement departs from the fill around it: outliers show here),
   ``log(B / reference_depth)``, ``k / 8`` and ``[IP-Basic gave B]``.
3. A U-Net: widths ``width * (1, 2, 4, 4, 8)``; one 3x3 convolution at full resolution, then
   per level a stride-2 and a plain 3x3 convolution with ReLU; the decoder upsamples
   (bilinear), concatenates the skip and convolves down to half resolution, then a 1x1
   convolution, upsampling and the full-resolution features *added* (no concatenation at
   full resolution: on a CPU it costs more than the convolutions). The input is padded
   (replicated) to a multiple of 16 and the output cropped back: any size works (7x13).
4. A 3x3 head gives two maps ``(r, u)``: ``D_c = B exp(3 tanh(r / 3))`` (metres, positive,
   within a factor 20 of the base) and ``U = 12 tanh(u / 12)`` (so sigma stays within
   ``exp(+-6)`` m). The head starts at zero: an untrained network returns ``D_c = B`` and
   ``U = 0`` (sigma 1 m).

**Loss** (:func:`densifier_loss`), over the set ``V`` of valid ground-truth pixels
(finite, ``0 < D <= max_depth``), with ``e = D_c - D``::

    L = 1/|V| sum_V |e|  +  w * 1/|V| sum_V [ 0.5 exp(-U) e^2 + 0.5 U ]

the reconstruction term (L1, metres) plus the Gaussian heteroscedastic term (the negative
log-likelihood of ``D`` under N(D_c, exp(U)) without its constant ``0.5 log 2 pi``), weight
``w`` (1 by default). The gradient flows through both terms into ``D_c`` and ``U``.

**Checkpoint** (:func:`save_densifier`, :func:`load_densifier`): the conventions of
:mod:`.checkpoint` with their own format tag (``sparsetools-densifier-checkpoint``): a plain
dict read back with ``torch.load(weights_only=True)`` from torch's zip format only, written
atomically, holding version, kind ``densifier``, the network's constructor arguments (checked
and bounded before anything is built), its weights (names and shapes checked against the
network built on torch's ``meta`` device), the training configuration, the run id, the
training history and the torch RNG state. A checkpoint of ``train`` (a depth network) is
refused with one line, and the reverse.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..errors import FormatError, ParameterError
from ..validate import (
    check_all_finite,
    check_array,
    check_dtype,
    check_int_range,
    check_positive,
    check_shape,
)
from .checkpoint_checks import RUN_ID, check_weights, load_weights, read_checkpoint_file
from .runtime import save_torch
from .url import URL_MODES

__all__ = [
    "CHECKPOINT_NAME",
    "DENSIFIER_FORMAT",
    "DENSIFIER_VERSION",
    "MAX_DENSIFIER_WIDTH",
    "DensifierCheckpoint",
    "LearnedDensifier",
    "SparseDensifier",
    "build_densifier",
    "check_densifier_record",
    "classical_base",
    "densifier_file",
    "densifier_loss",
    "densifier_record",
    "heteroscedastic_loss",
    "load_densifier",
    "open_densifier",
    "push_pull",
    "save_densifier",
]

DENSIFIER_FORMAT = "sparsetools-densifier-checkpoint"
DENSIFIER_VERSION = 1
#: The checkpoint's file name in a run folder (``--densifier RUN_DIR`` means this file).
CHECKPOINT_NAME = "densifier.pt"
#: Widths above this are refused in a checkpoint before any layer is allocated.
MAX_DENSIFIER_WIDTH = 256
#: Downsamplings of the U-Net (the input is padded to a multiple of 2 ** LEVELS).
LEVELS = 4
#: Bounds of the head: log(D_c / B) in +-R_MAX, U in +-U_MAX.
R_MAX, U_MAX = 3.0, 12.0
_MULTIPLIERS = (1, 2, 4, 4, 8)


# -- push-pull base ------------------------------------------------------------------------------


def push_pull(sparse: torch.Tensor, *, reference_depth: float) -> tuple[torch.Tensor, ...]:
    """Dense base of a sparse map by push-pull, the nearest measurement of a block winning
    (module docstring, step 1).

    Parameters
    ----------
    sparse : (B, 1, H, W) float tensor, metres
        0 (or any value <= 0) = no measurement.
    reference_depth : float, metres
        The base of a map without any measurement.

    Returns
    -------
    log_base : (B, 1, H, W) tensor
        ``log B``, B in metres.
    levels_up : (B, 1, H, W) tensor
        ``k``: 0 on measured pixels, the pyramid levels climbed to find a value elsewhere.
    """
    # -log S, -inf where empty: a max-pool keeps each block's nearest measurement (IP-Basic's
    # inversion before its dilations, for the same reason: foreground edges stay sharp)
    neg = torch.where(
        sparse > 0, -torch.log(sparse.clamp_min(1e-6)), torch.full_like(sparse, -math.inf)
    )
    levels = [neg]
    while min(levels[-1].shape[-2:]) > 1:
        levels.append(F.max_pool2d(levels[-1], 2, ceil_mode=True))
    top = levels[-1]
    has = torch.isfinite(top)
    value = torch.where(has, top, torch.full_like(top, -math.log(reference_depth)))
    up = (~has).to(sparse.dtype)
    for level in reversed(levels[:-1]):
        size = level.shape[-2:]
        coarse = F.interpolate(value, size=size, mode="bilinear", align_corners=False)
        coarse_up = F.interpolate(up, size=size, mode="nearest") + 1
        has = torch.isfinite(level)
        value = torch.where(has, level, coarse)
        up = torch.where(has, torch.zeros_like(coarse_up), coarse_up)
    return -value, up


# -- the network ---------------------------------------------------------------------------------


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.ReLU(inplace=True))


class SparseDensifier(nn.Module):
    """SpaDe-style network: sparse depth -> (coarse dense depth ``D_c``, log-variance ``U``).

    Parameters
    ----------
    width : int
        Channels of the full-resolution level (1 .. :data:`MAX_DENSIFIER_WIDTH`); the levels
        are ``width * (1, 2, 4, 4, 8)``.
    reference_depth : float, metres
        Scale of the log-depth inputs and the base of an empty map (> 0).

    Notes
    -----
    ``forward(sparse, base=None)`` takes a (B, 1, H, W) float tensor of metres (0 = no
    measurement) and, optionally, the classical fill of each map (:func:`classical_base`,
    (B, 1, H, W) metres, 0 = none; training and :class:`LearnedDensifier` always give it),
    and returns ``(depth, log_var)``, both (B, 1, H, W): ``D_c`` in metres (> 0) and
    ``U = log sigma^2`` (sigma in metres). See the module docstring for the layers.
    """

    def __init__(self, *, width: int = 8, reference_depth: float = 10.0):
        super().__init__()
        self.width = check_int_range(width, "width", low=1, high=MAX_DENSIFIER_WIDTH)
        self.reference_depth = check_positive(reference_depth, "reference_depth")
        ch = [width * m for m in _MULTIPLIERS]
        self.stem = _conv(5, ch[0])
        self.down = nn.ModuleList(
            nn.Sequential(_conv(ch[i], ch[i + 1], stride=2), _conv(ch[i + 1], ch[i + 1]))
            for i in range(LEVELS)
        )
        self.up = nn.ModuleList(_conv(ch[i + 1] + ch[i], ch[i]) for i in range(1, LEVELS))
        self.to_full = nn.Conv2d(ch[1], ch[0], 1)
        self.head = nn.Conv2d(ch[0], 2, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def config(self) -> dict:
        """The constructor arguments (saved in checkpoints)."""
        return {"width": self.width, "reference_depth": self.reference_depth}

    def features(
        self, sparse: torch.Tensor, base: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The (B, 5, H, W) input channels and ``log B`` (module docstring, steps 1-2)."""
        with torch.no_grad():
            log_fill, levels_up = push_pull(sparse, reference_depth=self.reference_depth)
            has_base = (base > 0).to(sparse.dtype) if base is not None else torch.zeros_like(sparse)
            if base is not None:
                log_fill = torch.where(base > 0, torch.log(base.clamp_min(1e-6)), log_fill)
            valid = (sparse > 0).to(sparse.dtype)
            log_s = torch.log(torch.where(valid > 0, sparse, torch.ones_like(sparse)))
            x = torch.cat(
                [
                    valid,
                    valid * (log_s - log_fill),
                    log_fill - math.log(self.reference_depth),
                    levels_up / 8.0,
                    has_base,
                ],
                dim=1,
            )
        return x, log_fill

    def forward(
        self, sparse: torch.Tensor, base: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if sparse.ndim != 4 or sparse.shape[1] != 1:
            raise ParameterError(f"must be (B, 1, H, W), got {tuple(sparse.shape)}", param="sparse")
        if base is not None and base.shape != sparse.shape:
            raise ParameterError(f"must have the shape of sparse, got {tuple(base.shape)}",
                                 param="base")  # fmt: skip
        h, w = sparse.shape[-2:]
        x, log_base = self.features(sparse, base)
        m = 2**LEVELS
        pad_h, pad_w = (-h) % m, (-w) % m
        if pad_h or pad_w:  # replicate: the padded border looks like the image's edge
            x = F.pad(x, (0, pad_w, 0, pad_h), mode="replicate")
        skips = [self.stem(x)]
        for block in self.down:
            skips.append(block(skips[-1]))
        y = skips[-1]
        for i in reversed(range(1, LEVELS)):
            skip = skips[i]
            y = F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            y = self.up[i - 1](torch.cat([y, skip], dim=1))
        # full resolution: no concatenation (the costliest step on a CPU), an addition
        y = F.interpolate(self.to_full(y), size=skips[0].shape[-2:], mode="bilinear",
                          align_corners=False)  # fmt: skip
        y = F.relu(y + skips[0])
        out = self.head(y)[..., :h, :w]
        r = R_MAX * torch.tanh(out[:, :1] / R_MAX)
        log_var = U_MAX * torch.tanh(out[:, 1:] / U_MAX)
        return torch.exp(log_base + r), log_var


def build_densifier(config: dict) -> SparseDensifier:
    """The network of a :meth:`SparseDensifier.config` dictionary."""
    try:
        return SparseDensifier(
            width=int(config["width"]), reference_depth=float(config["reference_depth"])
        )
    except KeyError as exc:
        raise ParameterError(f"densifier configuration lacks {exc.args[0]!r}") from None


def classical_base(sparse: np.ndarray) -> np.ndarray:
    """IP-Basic's fill of a sparse map (the paper's version), 0 where it gives no estimate:
    the network's base where defined (module docstring, step 1).

    Parameters
    ----------
    sparse : (H, W) float32, metres

    Returns
    -------
    (H, W) float32, metres
    """
    from ..ops.densify import ip_basic

    return ip_basic(sparse).depth


# -- loss ----------------------------------------------------------------------------------------


def _valid(gt: torch.Tensor, max_depth: float | None) -> torch.Tensor:
    m = torch.isfinite(gt) & (gt > 0)
    return m & (gt <= max_depth) if max_depth is not None else m


def heteroscedastic_loss(
    depth: torch.Tensor, log_var: torch.Tensor, gt: torch.Tensor, *, max_depth: float | None = None
) -> torch.Tensor:
    """Gaussian heteroscedastic term ``mean_V [0.5 exp(-U) (D_c - D)^2 + 0.5 U]``.

    Parameters
    ----------
    depth : (B, 1, H, W) tensor, metres
        ``D_c``.
    log_var : (B, 1, H, W) tensor, log of square metres
        ``U``.
    gt : (B, 1, H, W) tensor, metres
        ``D``; the mean runs over the valid pixels ``V`` (finite, ``0 < D <= max_depth``).
    max_depth : float, optional, metres

    Returns
    -------
    scalar tensor
        0 (still connected to the graph) when no pixel is valid.
    """
    if depth.shape != gt.shape or log_var.shape != gt.shape:
        raise ParameterError(
            f"depth {tuple(depth.shape)}, log_var {tuple(log_var.shape)} and gt "
            f"{tuple(gt.shape)} differ"
        )
    m = _valid(gt, max_depth)
    if not bool(m.any()):
        return depth.sum() * 0.0 + log_var.sum() * 0.0
    e = depth[m] - gt[m]
    u = log_var[m]
    return (0.5 * torch.exp(-u) * e * e + 0.5 * u).mean()


def densifier_loss(
    depth: torch.Tensor,
    log_var: torch.Tensor,
    gt: torch.Tensor,
    *,
    nll_weight: float = 1.0,
    max_depth: float | None = None,
) -> dict[str, torch.Tensor]:
    """SpaDe's loss: L1 reconstruction plus ``nll_weight`` times :func:`heteroscedastic_loss`.

    Returns
    -------
    dict
        ``l1`` (metres), ``nll`` and ``loss = l1 + nll_weight * nll`` (scalar tensors; the
        means run over the same valid pixels).
    """
    nll = heteroscedastic_loss(depth, log_var, gt, max_depth=max_depth)
    m = _valid(gt, max_depth)
    l1 = (depth[m] - gt[m]).abs().mean() if bool(m.any()) else depth.sum() * 0.0
    return {"l1": l1, "nll": nll, "loss": l1 + nll_weight * nll}


# -- checkpoint ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class DensifierCheckpoint:
    """A checked densifier checkpoint (:func:`load_densifier`).

    Attributes
    ----------
    path : Path
    model_config : dict
        :meth:`SparseDensifier.config`.
    model : dict of str to Tensor
        The network's weights.
    config : dict
        The training configuration (:class:`~.densifier_train.DensifierTrainConfig` as a dict).
    history : list of dict
        The training log (``metrics.csv``'s rows).
    run_id : str
    """

    path: Path
    model_config: dict
    model: dict
    config: dict
    history: list
    run_id: str


def save_densifier(
    path: Path, *, model: SparseDensifier, config: dict, history: list[dict], run_id: str
) -> None:
    """Write a densifier checkpoint atomically (the torch RNG state is taken now)."""
    obj = {
        "format": DENSIFIER_FORMAT,
        "version": DENSIFIER_VERSION,
        "kind": "densifier",
        "model_config": model.config(),
        "model": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "config": dict(config),
        "history": list(history),
        "run_id": str(run_id),
        "rng": {"torch": torch.get_rng_state()},
    }
    save_torch(obj, Path(path))


def _check_model_config(mc, path: Path) -> dict:
    if not isinstance(mc, dict):
        raise FormatError(f"{path}: model_config must be a mapping, got {type(mc).__name__}")
    width, ref = mc.get("width"), mc.get("reference_depth")
    if (
        isinstance(width, bool)
        or not isinstance(width, int)
        or not 1 <= width <= MAX_DENSIFIER_WIDTH
    ):
        raise FormatError(
            f"{path}: model_config width must be an integer from 1 to {MAX_DENSIFIER_WIDTH}, "
            f"got {str(width)[:40]}"
        )
    if isinstance(ref, bool) or not isinstance(ref, (int, float)) or not 0 < ref < math.inf:
        raise FormatError(f"{path}: model_config reference_depth must be a positive number")
    return {"width": width, "reference_depth": float(ref)}


def load_densifier(path: str | os.PathLike) -> DensifierCheckpoint:
    """Read and check a densifier checkpoint.

    Parameters
    ----------
    path : path-like
        ``densifier.pt``, or the run folder of ``train-densifier`` (its ``densifier.pt``).

    Returns
    -------
    DensifierCheckpoint

    Raises
    ------
    FormatError
        Missing, unreadable or foreign file (a ``train`` checkpoint, a legacy pickle file,
        anything else), a newer version, a model configuration of the wrong types or size,
        weights that do not fit it, a malformed run id or history (module docstring).
    """
    path = Path(path)
    if path.is_dir():
        path = path / CHECKPOINT_NAME
    if not path.is_file():
        raise FormatError(f"{path}: no such densifier checkpoint")
    raw = read_checkpoint_file(
        path,
        expected=DENSIFIER_FORMAT,
        what="sparsetools densifier checkpoint (train-densifier writes them)",
    )
    version = raw.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise FormatError(f"{path}: checkpoint version must be a positive integer")
    if version > DENSIFIER_VERSION:
        raise FormatError(f"{path}: checkpoint version {version} is newer than this sparsetools")
    rec = check_densifier_record(raw, path)  # model_config, weights and run_id, as embedded
    config, history = raw.get("config"), raw.get("history")
    if not isinstance(config, dict):
        raise FormatError(f"{path}: incomplete checkpoint (no training configuration)")
    if not isinstance(history, list) or not all(isinstance(r, dict) for r in history):
        raise FormatError(f"{path}: history must be a list of rows")
    return DensifierCheckpoint(path, rec["model_config"], rec["model"], config, history,
                               rec["run_id"])  # fmt: skip


def check_densifier_record(record, path: Path) -> dict:
    """The densifier a ``train --input rgbdu`` checkpoint carries
    (:func:`sparsetools.train.densifier.densifier_record`), checked as :func:`load_densifier` checks
    a file: ``model_config``, ``model`` and ``run_id``.

    Raises
    ------
    FormatError
        Missing, of the wrong types or size, or weights that do not fit (naming ``path``).
    """
    if not isinstance(record, dict):
        raise FormatError(f"{path}: a URL checkpoint without its densifier")
    mc = _check_model_config(record.get("model_config"), path)
    check_weights(record.get("model"), lambda: build_densifier(mc), path, "densifier")
    run_id = record.get("run_id")
    if not (isinstance(run_id, str) and RUN_ID.fullmatch(run_id)):
        raise FormatError(f"{path}: the densifier's run_id must be 32 hex digits")
    return {"model_config": mc, "model": record["model"], "run_id": run_id}


# -- inference -----------------------------------------------------------------------------------


@contextlib.contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """torch's CPU thread count set to ``threads`` for a block, then restored."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(threads))
    try:
        yield
    finally:
        torch.set_num_threads(before)


class LearnedDensifier:
    """A trained densifier as ``densify --method learned`` runs it (picklable, CPU).

    The checkpoint is read and checked when the object is made (a bad file fails before any
    output is written); the weights travel with the object to worker processes and the
    network is built there on first use.

    Parameters
    ----------
    checkpoint : path-like
        ``densifier.pt`` or its run folder.
    threads : int
        torch CPU threads per call (default 1: one core per worker process).
    """

    def __init__(self, checkpoint: str | os.PathLike, *, threads: int = 1):
        ckpt = load_densifier(checkpoint)
        self.path = ckpt.path
        self.model_config = ckpt.model_config
        self.weights = ckpt.model
        self.run_id = ckpt.run_id
        self.max_depth = ckpt.config.get("max_depth")
        self.threads = check_int_range(threads, "threads", low=1)
        self._net: SparseDensifier | None = None

    @classmethod
    def from_record(cls, record: dict, *, path: Path, threads: int = 1) -> LearnedDensifier:
        """The densifier a URL checkpoint carries (:func:`check_densifier_record`'s output),
        without reading its file; ``path`` (the checkpoint) is named in errors."""
        self = cls.__new__(cls)
        self.path = Path(path)
        self.model_config = dict(record["model_config"])
        self.weights = record["model"]
        self.run_id = record["run_id"]
        self.max_depth = None
        self.threads = check_int_range(threads, "threads", low=1)
        self._net = None
        return self

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_net"] = None
        return state

    def network(self) -> SparseDensifier:
        """The network with its weights, in evaluation mode (built once per process)."""
        if self._net is None:
            net = build_densifier(self.model_config)
            load_weights(net, self.weights, self.path, "densifier")
            self._net = net.eval()
        return self._net

    def densify(self, sparse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coarse dense depth and log-variance of one sparse map.

        Parameters
        ----------
        sparse : (H, W) float array, metres
            0 (or <= 0) = no measurement.

        Returns
        -------
        depth : (H, W) float32, metres
            ``D_c``, > 0 on every pixel.
        log_var : (H, W) float32, log of square metres
            ``U = log sigma^2``.

        Raises
        ------
        ParameterError
            Not an (H, W) float array, or NaN / Inf in it.
        """
        check_array(sparse, "sparse")
        check_shape(sparse, "(H, W)", "sparse", nonempty=True)
        check_dtype(sparse, "sparse", "f")
        check_all_finite(sparse, "sparse")
        sparse = np.ascontiguousarray(sparse, dtype=np.float32)
        base = torch.from_numpy(classical_base(np.maximum(sparse, 0)))[None, None]
        x = torch.from_numpy(sparse)[None, None]
        with torch_threads(self.threads), torch.inference_mode():
            depth, log_var = self.network()(x, base)
        return depth[0, 0].numpy().copy(), log_var[0, 0].numpy().copy()


# -- the densifier of a URL run (train --input rgbdu) ----------------------------------------


def densifier_file(path) -> Path:
    """The densifier checkpoint a ``--densifier`` value names (a run folder: its
    ``densifier.pt``)."""
    path = Path(path)
    return path / CHECKPOINT_NAME if path.is_dir() else path


def open_densifier(config, ckpt=None):
    """The densifier that computes a run's ``D_c`` and ``U`` (None outside a URL mode).

    Parameters
    ----------
    config : TrainConfig
        Checked (:func:`~.url.check_url_settings`).
    ckpt : Checkpoint, optional
        The run's checkpoint (``--resume``, ``eval``, ``predict``): its embedded densifier
        is used and the ``--densifier`` file is not read.

    Returns
    -------
    LearnedDensifier or None
        One torch thread per call.

    Raises
    ------
    FormatError
        A missing or foreign densifier checkpoint (one line naming it), or a checkpoint of a
        URL run without its densifier.
    """
    if config.input_mode not in URL_MODES:
        return None
    if ckpt is None:
        return LearnedDensifier(config.densifier)
    if ckpt.densifier is None:
        raise FormatError(f"{ckpt.path}: a URL checkpoint without its densifier")
    return LearnedDensifier.from_record(ckpt.densifier, path=ckpt.path)


def densifier_record(densifier) -> dict:
    """What a checkpoint keeps of a :class:`LearnedDensifier`: its constructor
    arguments (``model_config``), weights (``model``) and ``run_id``."""
    return {
        "model_config": dict(densifier.model_config),
        "model": dict(densifier.weights),
        "run_id": densifier.run_id,
    }
