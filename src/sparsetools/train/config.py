"""The settings of a training run: :class:`TrainConfig`, its checks, the resume rule, the schedule.

One configuration serves both kinds of training:

- supervised depth completion (``selfsup=None``): the loss ``loss`` on valid ground truth;
- self-supervised training from video (``selfsup=SelfSupSettings(...)``): photometric
  reconstruction of the target frame from its neighbours, optionally with a sparse-LiDAR loss
  (METHODS.md section 8, :mod:`sparsetools.train.selfsup`).

A configuration is saved in ``config.json`` and in every checkpoint (:meth:`TrainConfig.to_dict`,
flat JSON with the self-supervised settings nested under ``selfsup``). ``--resume`` continues a
run with its saved configuration; only :attr:`TrainConfig.RESUMABLE` fields may change
(:func:`resumed_config`).

Configurations read back from a file (``config.json``, a checkpoint) are untrusted:
:meth:`TrainConfig.from_dict` and :meth:`TrainConfig.validate` check the type of every field
(a string width, a list learning rate, a bool epoch count are refused with the field named) and
bound the network's size (:data:`MAX_WIDTH`) before anything is built from them.
"""

from __future__ import annotations

import math
import numbers
import typing
from dataclasses import asdict, dataclass, fields, replace

from ..errors import ParameterError
from .losses import LOSSES
from .model import (
    DEFAULT_LIDAR_SCALES,
    INPUT_CHANNELS,
    LIDAR_ENCODERS,
    LIDAR_SCALES,
    check_lidar_scales,
)
from .runtime import resolve_device
from .url import GATE_ALPHA, GATE_BETA, check_url_settings

__all__ = [
    "CAMERA_FREE_MODES",
    "CONFIDENCE_MODES",
    "FIELD_OPTIONS",
    "MAX_WIDTH",
    "SELECT_BY",
    "SPARSE_LOSSES",
    "SelfSupSettings",
    "TrainConfig",
    "epoch_lr",
    "option_of",
    "resumed_config",
]

#: Sparse-LiDAR losses of self-supervised training ("none" = camera only, scale-ambiguous).
SPARSE_LOSSES = ("none", "l1", "silog")
#: How a self-supervised run picks ``best.pt``: validation photometric loss (no ground truth
#: read), or validation RMSE against ground truth.
SELECT_BY = ("photometric", "gt")
#: Input modes that feed the confidence map of ``dataset build --confidence`` to the network.
CONFIDENCE_MODES = ("rgbdc",)
#: Input modes without the camera image (the radar paper's radar-only baseline).
CAMERA_FREE_MODES = ("d",)
#: Largest first-level width of the depth and pose networks. The U-Net has about
#: 10,140 x width^2 parameters (10.4 M at 32, the paper's width; 41.5 M at 64): 256 gives
#: 665 M (2.7 GB of float32 weights, three times that with Adam's moments). A checkpoint or
#: configuration asking for more is refused before any layer is allocated.
MAX_WIDTH = 256


#: The command-line option of each field whose option is spelt otherwise (0.3 renamed the
#: options; the fields keep their 0.2.0 names so that the runs of 0.2.0 resume).
FIELD_OPTIONS = {"crop": "--crop-size", "workers": "--loader-workers"}


def option_of(name: str) -> str:
    """The parameter name errors about field ``name`` carry: its option where it is spelt
    otherwise (``crop`` -> ``--crop-size``), else the field name (``max_depth``)."""
    return FIELD_OPTIONS.get(name, name)


def _short(value) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_pair(check):
    return lambda v: isinstance(v, (list, tuple)) and len(v) == 2 and all(map(check, v))


#: What a field of each annotated type accepts (JSON / checkpoint values are checked against
#: these), and how the error message says it. A field of a type missing here is refused when
#: this module is imported (:func:`_field_kinds`): a new field cannot go unchecked.
_KINDS = {
    str: (lambda v: isinstance(v, str), "a string"),
    str | None: (lambda v: v is None or isinstance(v, str), "a string or null"),
    int: (_is_int, "an integer"),
    int | None: (lambda v: v is None or _is_int(v), "an integer or null"),
    float: (_is_real, "a number"),
    float | None: (lambda v: v is None or _is_real(v), "a number or null"),
    tuple[int, ...]: (
        lambda v: isinstance(v, (list, tuple)) and all(map(_is_int, v)),
        "a list of integers",
    ),
    bool: (lambda v: isinstance(v, bool), "true or false"),
    tuple[int, int] | None: (lambda v: v is None or _is_pair(_is_int)(v), "null or two integers"),
    tuple[float, float]: (_is_pair(_is_real), "two numbers"),
}


def _field_kinds(cls, *, skip: tuple[str, ...] = ()) -> dict[str, tuple]:
    """Field name -> (accepts, wanted) of every dataclass field of ``cls`` but ``skip``, from
    its annotation (:data:`_KINDS`).

    Raises
    ------
    TypeError
        A field whose annotated type has no entry in :data:`_KINDS`.
    """
    hints = typing.get_type_hints(cls)
    kinds = {}
    for f in fields(cls):
        if f.name in skip:
            continue
        kind = _KINDS.get(hints[f.name])
        if kind is None:
            raise TypeError(
                f"{cls.__name__}.{f.name}: no check for values of type {hints[f.name]} "
                "(add it to sparsetools.train.config._KINDS)"
            )
        kinds[f.name] = kind
    return kinds


def _check_types(obj, kinds: dict[str, tuple]) -> None:
    """Raise :class:`ParameterError` naming the first field of ``obj`` of the wrong type."""
    for name, (accepts, wanted) in kinds.items():
        value = getattr(obj, name)
        if not accepts(value):
            raise ParameterError(
                f"{name} must be {wanted}, got {_short(value)}", param=option_of(name)
            )


def _mapping(d, what: str) -> dict:
    if not isinstance(d, dict):
        raise ParameterError(f"{what} must be a mapping, got {type(d).__name__}")
    return d


@dataclass(frozen=True)
class SelfSupSettings:
    """Settings of self-supervised training from frame triplets (t-1, t, t+1).

    Parameters
    ----------
    sparse_loss : {'none', 'l1', 'silog'}
        EffisDepth's sparse loss on the pixels with valid sparse depth; it gives the model
        metric scale. ``'none'``: camera only (evaluated with per-image median scaling).
    sparse_weight : float
        Weight of the sparse loss against the photometric loss.
    silog_lambda : float
        lambda of the SILog sparse loss ``10 sqrt(mean d^2 - lambda (mean d)^2)``; < 1 keeps a
        penalty on the scale.
    smoothness : float
        Weight of the edge-aware smoothness (monodepth2: 1e-3), divided by 2^scale.
    scales : int
        Decoder outputs used by the losses (1-4; monodepth2: 4).
    depth_range : (min, max), metres
        Depth of the sigmoid output: 1 / (1/max + (1/min - 1/max) sigma) (monodepth2: 0.1, 100).
    auto_mask : bool
        monodepth2's auto-masking (identity reprojection).
    mcie : bool
        RNW: photometric loss on MCIE-enhanced frames, one table per triplet built from the
        target frame (:func:`sparsetools.ops.enhance.mcie_lut`).
    mcie_clip : float
        MCIE clip limit (fraction of the pixel count; RNW 0.004).
    sbm : bool
        RNW's statistics-based mask, combined with the auto-mask.
    sbm_beta : float
        EWMA factor of the SBM threshold (RNW: 0.98).
    sbm_percentile : float
        Percentile (0-100) of the per-pixel temporal change that the threshold tracks.
    pose_width : int
        Width of the first level of the pose network.
    pose_lidar_encoder : {'none', 'sfe', 'dense'}
        LiDAR branch of the pose network (EffisDepth's "SFE in depth and pose"): the two
        frames' sparse depth maps through an SFE (or its dense twin) whose features are added
        to the pose encoder's first five levels (:mod:`sparsetools.train.selfsup.pose_net`).
    pose_translation_scale : float, optional
        Factor on the pose network's raw translation. None (default): monodepth2's 0.01 for
        camera-only runs, and for runs with the sparse loss the factor that gives them the
        same initial flow t / z
        (:func:`sparsetools.train.selfsup.pose_net.metric_translation_scale`, 0.5 for the
        10 m start and 0.1-100 m). Configurations written before 0.4 lack the key and keep
        0.01.
    pose_failure_ratio : float
        A run whose last validation ATE (per-snippet scaled) is above this fraction of the ATE
        of predicting no motion is flagged as a pose failure (log and summary); 1 = the pose
        network explains none of the motion. Needs true poses in the validation split.
    lidar_dropout : float
        Fraction of training batches whose LiDAR input (the depth network's branch, or the
        sparse channels of ``--input rgbd``) is an empty map; the sparse loss still sees the
        points. Drawn from ``(seed, step)``.
    lidar_holdout : float
        Fraction of each frame's sparse points withheld from the LiDAR input during training
        and used only by the sparse loss (the others feed the input only): disjoint point sets,
        so the network cannot pass its input straight to the loss. 0 = every point both.
    select_by : {'photometric', 'gt'}
        ``best.pt`` by the validation photometric loss (default; reads no ground truth) or by
        the validation RMSE against ground truth (needs it in every validation frame).
        Configurations written before 0.4 lack the key and keep ``'gt'``.
    pbr, pbr_coordinates, pbr_weight, pbr_discriminator_weight
        RNW's priors-based regularization (:mod:`sparsetools.train.selfsup.pbr`): the folder
        of a dataset whose ground truth (or dense depth) are unpaired reference depths (None:
        off); the coordinate image I_p in the discriminator's input; xi, weight of L_G in the
        depth network's loss; tau, weight of L_D in the discriminator's own loss.
    """

    sparse_loss: str = "none"
    sparse_weight: float = 0.1
    silog_lambda: float = 0.85
    smoothness: float = 1e-3
    scales: int = 4
    depth_range: tuple[float, float] = (0.1, 100.0)
    auto_mask: bool = True
    mcie: bool = False
    mcie_clip: float = 0.004
    sbm: bool = False
    sbm_beta: float = 0.98
    sbm_percentile: float = 10.0
    pose_width: int = 16
    pose_lidar_encoder: str = "none"
    pose_translation_scale: float | None = None
    pose_failure_ratio: float = 0.5
    lidar_dropout: float = 0.0
    lidar_holdout: float = 0.0
    select_by: str = "photometric"
    pbr: str | None = None
    pbr_coordinates: bool = True
    pbr_weight: float = 0.01
    pbr_discriminator_weight: float = 1.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["depth_range"] = list(self.depth_range)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> SelfSupSettings:
        """Settings from :meth:`to_dict` output; unknown keys are ignored, missing ones default.

        Raises
        ------
        ParameterError
            ``d`` is not a mapping, or a value has the wrong type (ranges are checked by
            :meth:`validate`).
        """
        d = _mapping(d, "the self-supervised settings (selfsup)")
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        # settings written before 0.4 meant monodepth2's translation scale and GT selection
        kw.setdefault("pose_translation_scale", 0.01)
        kw.setdefault("select_by", "gt")
        pair = kw.get("depth_range")
        if isinstance(pair, (list, tuple)) and all(map(_is_real, pair)):
            kw["depth_range"] = tuple(float(v) for v in pair)
        settings = cls(**kw)
        _check_types(settings, _SELFSUP_KINDS)
        return settings

    def validate(self) -> None:
        """Raise :class:`ParameterError` (naming the setting) for a bad type or a value out of
        range."""
        _check_types(self, _SELFSUP_KINDS)
        if self.sparse_loss not in SPARSE_LOSSES:
            raise ParameterError(
                f"unknown sparse loss {self.sparse_loss!r}; choose one of {', '.join(SPARSE_LOSSES)}",
                param="sparse_loss",
            )
        for name in ("sparse_weight", "smoothness", "mcie_clip"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise ParameterError(f"{name} must be a finite number >= 0, got {v}", param=name)
        if self.mcie_clip <= 0:
            raise ParameterError("mcie_clip must be > 0", param="mcie_clip")
        if not 0 <= self.silog_lambda <= 1:
            raise ParameterError(
                f"silog_lambda must be in [0, 1], got {self.silog_lambda}", param="silog_lambda"
            )
        if not 1 <= int(self.scales) <= 4:
            raise ParameterError(f"scales must be 1-4, got {self.scales}", param="scales")
        lo, hi = self.depth_range
        if not (0 < lo < hi and math.isfinite(hi)):
            raise ParameterError(
                f"depth_range must satisfy 0 < min < max < inf, got {self.depth_range}",
                param="depth_range",
            )
        if not 0 <= self.sbm_beta < 1:
            raise ParameterError(
                f"sbm_beta must be in [0, 1), got {self.sbm_beta}", param="sbm_beta"
            )
        if not 0 <= self.sbm_percentile <= 100:
            raise ParameterError(
                f"sbm_percentile must be in [0, 100], got {self.sbm_percentile}",
                param="sbm_percentile",
            )
        if not 1 <= self.pose_width <= MAX_WIDTH:
            raise ParameterError(
                f"pose_width must be 1-{MAX_WIDTH}, got {self.pose_width}", param="pose_width"
            )
        if self.pose_lidar_encoder not in LIDAR_ENCODERS:
            raise ParameterError(
                f"unknown pose LiDAR encoder {self.pose_lidar_encoder!r}; choose one of "
                f"{', '.join(LIDAR_ENCODERS)}",
                param="pose_lidar_encoder",
            )
        scale = self.pose_translation_scale
        if scale is not None and not (scale > 0 and math.isfinite(scale)):
            raise ParameterError(
                f"pose_translation_scale must be a positive number, got {scale}",
                param="pose_translation_scale",
            )
        if not 0 < self.pose_failure_ratio <= 1:
            raise ParameterError(
                f"pose_failure_ratio must be in (0, 1], got {self.pose_failure_ratio}",
                param="pose_failure_ratio",
            )
        for name in ("lidar_dropout", "lidar_holdout"):
            if not 0 <= getattr(self, name) < 1:
                raise ParameterError(
                    f"{name} must be in [0, 1), got {getattr(self, name)}", param=name
                )
        if self.select_by not in SELECT_BY:
            raise ParameterError(
                f"unknown model selection {self.select_by!r}; choose one of {', '.join(SELECT_BY)}",
                param="select_by",
            )
        self._validate_pbr()

    def _validate_pbr(self) -> None:
        xi, tau = float(self.pbr_weight), float(self.pbr_discriminator_weight)
        for name, v, bound in (
            ("pbr_weight", xi, ">= 0"),
            ("pbr_discriminator_weight", tau, "> 0"),
        ):
            if not (math.isfinite(v) and (v >= 0 if bound == ">= 0" else v > 0)):
                raise ParameterError(f"{name} must be a finite number {bound}, got {v}", param=name)
        if self.pbr is not None and not self.pbr.strip():
            raise ParameterError("the PBR reference must be a dataset folder", param="pbr")
        off = SelfSupSettings()
        if self.pbr is None and (self.pbr_coordinates, xi, tau) != (
            off.pbr_coordinates,
            off.pbr_weight,
            off.pbr_discriminator_weight,
        ):
            raise ParameterError(
                "--pbr REFERENCE is missing: --pbr-weight, --pbr-discriminator-weight and "
                "--no-pbr-coordinates are settings of the priors-based regularization",
                param="pbr",
            )

    @property
    def metric_scale(self) -> bool:
        """True when the sparse loss fixes the scale (no median scaling in evaluation)."""
        return self.sparse_loss != "none"


#: The check of every field of :class:`SelfSupSettings` (see :func:`_check_types`).
_SELFSUP_KINDS = _field_kinds(SelfSupSettings)


@dataclass
class TrainConfig:
    """Everything that defines a training run (saved in ``config.json`` and checkpoints).

    ``crop`` is (height, width); ``max_steps`` caps the total number of optimizer steps.
    ``workers``, ``device`` and ``threads`` do not change the results on CPU. ``selfsup``
    selects self-supervised training (None: supervised, with ``loss`` on ground truth).
    ``lidar_encoder`` (``'none'``, ``'sfe'``, ``'dense'``) adds a LiDAR branch to the depth
    network (:mod:`sparsetools.train.model`; EffisDepth's layout, so ``input_mode`` must then
    be ``'rgb'``) that feeds the encoder levels of ``lidar_scales`` (default 1/2 .. 1/16;
    configurations written before 0.4 lack the key and fed every level, 1 .. 1/16).
    ``url`` (``'residual'``, ``'gated'``), ``densifier`` (its checkpoint) and the gate's
    ``gate_alpha``, ``gate_beta`` belong to ``input_mode='rgbdu'`` (:mod:`sparsetools.train.url`).
    """

    dataset: str
    out_dir: str
    input_mode: str = "rgbd"
    loss: str = "l1"
    epochs: int = 20
    batch_size: int = 8
    lr: float = 1e-3
    optimizer: str = "adam"
    lr_schedule: str = "constant"
    lr_step: int = 5
    lr_gamma: float = 0.5
    crop: tuple[int, int] | None = None
    seed: int = 0
    width: int = 32
    final_layer: bool = False
    workers: int = 0
    max_steps: int | None = None
    device: str = "cpu"
    train_split: str = "train"
    val_split: str = "val"
    max_depth: float = 80.0
    pictures: int = 3
    threads: int | None = None
    scale_range: tuple[float, float] = (1.0, 1.0)
    jitter: float = 0.2
    lidar_encoder: str = "none"
    lidar_scales: tuple[int, ...] = DEFAULT_LIDAR_SCALES
    url: str | None = None
    densifier: str | None = None
    gate_alpha: float = GATE_ALPHA
    gate_beta: float = GATE_BETA
    selfsup: SelfSupSettings | None = None

    #: Fields that may change when a run is resumed (they do not alter the maths).
    RESUMABLE = ("epochs", "max_steps", "workers", "device", "threads", "pictures")

    @property
    def self_supervised(self) -> bool:
        return self.selfsup is not None

    def to_dict(self) -> dict:
        d = asdict(self)
        d["crop"] = list(self.crop) if self.crop is not None else None
        d["scale_range"] = list(self.scale_range)
        d["lidar_scales"] = list(self.lidar_scales)
        d["selfsup"] = self.selfsup.to_dict() if self.selfsup is not None else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """A configuration from :meth:`to_dict` output (``config.json``, a checkpoint).

        Unknown keys are ignored and missing ones take their defaults (files of older
        versions), except ``dataset`` and ``out_dir``. Every value's type is checked; ranges
        and consistency are :meth:`validate`'s.

        Raises
        ------
        ParameterError
            ``d`` is not a mapping, lacks ``dataset`` or ``out_dir``, or a value has the wrong
            type (naming the field).
        """
        d = _mapping(d, "a training configuration")
        names = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in names}
        for required in ("dataset", "out_dir"):
            if required not in kw:
                raise ParameterError(f"the training configuration lacks {required!r}")
        if kw.get("lidar_encoder", "none") != "none":
            kw.setdefault("lidar_scales", LIDAR_SCALES)  # before 0.4: every level
        for name in ("crop", "scale_range", "lidar_scales"):  # JSON lists -> tuples
            if isinstance(kw.get(name), list):
                kw[name] = tuple(kw[name])
        if isinstance(kw.get("scale_range"), tuple) and all(map(_is_real, kw["scale_range"])):
            kw["scale_range"] = tuple(float(v) for v in kw["scale_range"])
        if kw.get("selfsup") is not None:
            kw["selfsup"] = SelfSupSettings.from_dict(kw["selfsup"])
        config = cls(**kw)
        _check_types(config, _CONFIG_KINDS)
        return config

    def validate(self) -> None:
        """Raise :class:`ParameterError` (naming the setting) for a value of the wrong type,
        out of range, or inconsistent with another one."""
        _check_types(self, _CONFIG_KINDS)
        if self.selfsup is not None and not isinstance(self.selfsup, SelfSupSettings):
            raise ParameterError(
                f"selfsup must be SelfSupSettings or None, got {type(self.selfsup).__name__}",
                param="selfsup",
            )
        if self.input_mode not in INPUT_CHANNELS:
            raise ParameterError(
                f"unknown input mode {self.input_mode!r}; choose one of {sorted(INPUT_CHANNELS)}",
                param="input_mode",
            )
        check_url_settings(self)
        if self.loss not in LOSSES:
            raise ParameterError(
                f"unknown loss {self.loss!r}; choose one of {sorted(LOSSES)}", param="loss"
            )
        if self.lr_schedule not in ("constant", "step", "cosine"):
            raise ParameterError(
                f"unknown learning-rate schedule {self.lr_schedule!r}; "
                "choose constant, step or cosine",
                param="lr_schedule",
            )
        if self.lr_step < 1 or not 0 < self.lr_gamma <= 1:
            raise ParameterError(
                f"need lr_step >= 1 and 0 < lr_gamma <= 1, got {self.lr_step}, {self.lr_gamma}",
                param="lr_gamma" if self.lr_step >= 1 else "lr_step",
            )
        if self.optimizer not in ("adam", "sgd"):
            raise ParameterError(
                f"unknown optimizer {self.optimizer!r}; choose adam or sgd", param="optimizer"
            )
        for name in ("epochs", "batch_size", "width"):
            if getattr(self, name) < 1:
                raise ParameterError(f"{name} must be >= 1, got {getattr(self, name)}", param=name)
        if self.width > MAX_WIDTH:
            raise ParameterError(
                f"width must be at most {MAX_WIDTH} (about {10_140 * self.width**2:.3g} "
                f"parameters asked for), got {self.width}",
                param="width",
            )
        if not 0 <= self.seed < 2**63:
            raise ParameterError(f"seed must be in [0, 2^63), got {self.seed}", param="seed")
        if self.threads is not None and self.threads < 1:
            raise ParameterError(f"threads must be >= 1, got {self.threads}", param="threads")
        if not (0 <= self.jitter < 1):
            raise ParameterError(f"jitter must be in [0, 1), got {self.jitter}", param="jitter")
        if not (self.lr > 0 and math.isfinite(self.lr)):
            raise ParameterError(f"learning rate must be positive, got {self.lr}", param="lr")
        if self.max_steps is not None and self.max_steps < 1:
            raise ParameterError(f"max_steps must be >= 1, got {self.max_steps}", param="max_steps")
        if self.workers < 0:
            raise ParameterError(
                f"workers must be >= 0, got {self.workers}", param=option_of("workers")
            )
        if not (self.max_depth > 0 and math.isfinite(self.max_depth)):
            raise ParameterError(
                f"max_depth must be positive, got {self.max_depth}", param="max_depth"
            )
        if self.pictures < 0:
            raise ParameterError(f"pictures must be >= 0, got {self.pictures}", param="pictures")
        if self.crop is not None and (len(self.crop) != 2 or min(self.crop) < 1):
            raise ParameterError(
                f"crop must be two positive sizes (H, W), got {self.crop}", param=option_of("crop")
            )
        if self.lidar_encoder not in LIDAR_ENCODERS:
            raise ParameterError(
                f"unknown LiDAR encoder {self.lidar_encoder!r}; choose one of "
                f"{', '.join(LIDAR_ENCODERS)}",
                param="lidar_encoder",
            )
        check_lidar_scales(self.lidar_scales)
        if self.lidar_encoder != "none" and self.input_mode != "rgb":
            raise ParameterError(
                f"--lidar-encoder {self.lidar_encoder} takes the sparse depth into its own "
                f"branch and the image alone into the U-Net (EffisDepth): use --input rgb, "
                f"not {self.input_mode}",
                param="input_mode",
            )
        resolve_device(self.device)
        if self.selfsup is not None:
            if self.input_mode in CAMERA_FREE_MODES:
                raise ParameterError(
                    f"--input {self.input_mode} gives the depth network no camera image, but "
                    "self-supervised training learns from the image (photometric loss): use "
                    "--input rgb, rgbd or rgbdm",
                    param="--input",
                )
            if self.input_mode in CONFIDENCE_MODES:
                raise ParameterError(
                    f"--input {self.input_mode} is for supervised training: the frame "
                    "triplets of self-supervised training carry no confidence map; use "
                    "--input rgbd",
                    param="--input",
                )
            self.selfsup.validate()
            takes_lidar = self.lidar_encoder != "none" or self.input_mode in ("rgbd", "rgbdm")
            for name in ("lidar_dropout", "lidar_holdout"):
                if getattr(self.selfsup, name) > 0 and not takes_lidar:
                    raise ParameterError(
                        f"--{name.replace('_', '-')} acts on the depth network's LiDAR input, "
                        f"and --input {self.input_mode} without --lidar-encoder has none",
                        param=name,
                    )
            if self.selfsup.lidar_holdout > 0 and not self.selfsup.metric_scale:
                raise ParameterError(
                    "--lidar-holdout gives points to the sparse loss: add --sparse-loss",
                    param="lidar_holdout",
                )
            if self.final_layer:
                raise ParameterError(
                    "the final adjustment layer works on metric depth; self-supervised "
                    "training predicts disparity: leave --final-layer off",
                    param="final_layer",
                )
            if self.scale_range != (1.0, 1.0):
                raise ParameterError(
                    "scale augmentation changes the geometry between frames: not available "
                    "in self-supervised training",
                    param="scale_range",
                )


#: The check of every field of :class:`TrainConfig` but ``selfsup`` (checked as settings).
_CONFIG_KINDS = _field_kinds(TrainConfig, skip=("selfsup",))


def _flat(config: TrainConfig) -> dict:
    """The configuration with the self-supervised settings as ``selfsup.NAME`` entries."""
    d = config.to_dict()
    nested = d.pop("selfsup")
    d["self_supervised"] = nested is not None
    for k, v in (nested or {}).items():
        d[f"selfsup.{k}"] = v
    return d


def _crop_text(crop) -> str:
    """A configuration's crop ``[H, W]`` as ``--crop-size`` text (``WxH``), or ``none``."""
    return "none" if crop is None else f"{crop[1]}x{crop[0]} (WxH)"


def resumed_config(
    config: TrainConfig, saved: TrainConfig, explicit: set[str] | None
) -> TrainConfig:
    """The saved configuration of a run, with the fields that may change taken from ``config``.

    Parameters
    ----------
    config : TrainConfig
        What the caller asked for now.
    saved : TrainConfig
        The run's configuration (from its checkpoint).
    explicit : set of str, optional
        Fields the user set explicitly (``selfsup.NAME`` for self-supervised settings,
        ``self_supervised`` for the mode); only those are compared. Default: every field
        that is not resumable.

    Raises
    ------
    ParameterError
        An explicitly given setting differs from the run's (naming the setting).
    """
    mine, theirs = _flat(config), _flat(saved)
    check = explicit if explicit is not None else set(mine) - set(TrainConfig.RESUMABLE)
    for name in sorted(check):
        if name in TrainConfig.RESUMABLE or name in ("dataset", "out_dir"):
            continue
        if name not in theirs:  # a field this run's version did not have
            continue
        if mine.get(name) != theirs[name]:
            if name == "input_mode":
                raise ParameterError(
                    f"the run in {config.out_dir} was trained with input mode "
                    f"'{theirs[name]}', not '{mine[name]}': a checkpoint cannot change its "
                    "input mode",
                    param="input_mode",
                )
            if name == "self_supervised":
                kind = "self-supervised" if theirs[name] else "supervised"
                raise ParameterError(
                    f"the run in {config.out_dir} is a {kind} run: --resume cannot change "
                    "the kind of training",
                    param="self_supervised",
                )
            if name == "crop":  # as --crop-size writes it
                theirs_text, mine_text = _crop_text(theirs[name]), _crop_text(mine.get(name))
                raise ParameterError(
                    f"--resume continues the run's own settings: the crop is {theirs_text} "
                    f"there, not {mine_text}",
                    param=option_of(name),
                )
            raise ParameterError(
                f"--resume continues the run's own settings: {name} is {theirs[name]!r} "
                f"there, not {mine.get(name)!r}",
                param=option_of(name.split(".")[-1]),
            )
    return replace(
        saved,
        dataset=config.dataset,
        out_dir=config.out_dir,
        **{name: getattr(config, name) for name in TrainConfig.RESUMABLE},
    )


def epoch_lr(config: TrainConfig, epoch: int) -> float:
    """Learning rate of (0-based) ``epoch``: a pure function of the configuration and epoch.

    ``constant``: ``lr``; ``step``: ``lr * lr_gamma ** (epoch // lr_step)`` (Ma & Karaman);
    ``cosine``: from ``lr`` down to ``lr / 100`` over ``epochs`` (so a resumed run with a larger
    ``epochs`` follows a new, longer schedule).
    """
    if config.lr_schedule == "step":
        return config.lr * config.lr_gamma ** (epoch // config.lr_step)
    if config.lr_schedule == "cosine":
        t = min(epoch / max(config.epochs - 1, 1), 1.0)
        return config.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))
    return config.lr
