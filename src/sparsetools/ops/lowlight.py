"""Low-light image synthesis after DepthDark's LLDG (arXiv 2507.18243), METHODS.md section 4.

    I_F  = (s_b I)^g + sum_i [ss(L; s_F, P_i)]^g        (linear light)
    I_FN = ELD noise of I_F, in raw units x = I_F * saturation / ratio
    out  = clip(I_FN, 0, 1)^(1/g)                        (back to 8-bit)

``I`` is the day image in [0, 1], ``s_b`` the brightness scale, ``g`` the random linearisation
gamma, ``L`` flare patterns from a procedural bank (:mod:`.flare`) and the noise the ELD
physics model (:mod:`.noise`). Every sampled value goes into a :class:`LowLightRecord`, a
plain JSON-serialisable dataclass; ``lowlight(image, record=record)`` replays it exactly
(the noise is regenerated from the recorded seed).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_all_finite,
    check_array,
    check_choice,
    check_dtype,
    check_flag,
    check_instance,
    check_pair,
    check_positive,
    check_shape,
)
from .flare import BANK_VERSION, FlareBank, FlareRecord, flare_bank, render_flares, sample_flares
from .noise import CAMERA_PROFILES, NOISE_MODELS, NoiseParams, add_sensor_noise, sample_noise_params

__all__ = ["RECORD_VERSION", "LowLightParams", "LowLightRecord", "lowlight"]

#: Version of the record layout (stored in every record).
RECORD_VERSION = 1


@dataclass(frozen=True)
class LowLightParams:
    """Sampling ranges of :func:`lowlight` (METHODS.md section 4 defaults).

    Attributes
    ----------
    brightness : (float, float)
        ``s_b ~ U(low, high)``.
    gamma : (float, float)
        ``g ~ U(low, high)``: linearisation exponent (output uses 1/g).
    flare : bool
        Add flares.
    flare_scale : (float, float)
        ``s_F ~ logU``: pattern side as a fraction of the shorter image side. The paper's range
        is not public; 0.2-1.0 gives lamps of 75-375 px on a KITTI frame.
    flare_amount : (float, float)
        ``F ~ logU``; ``N_F = max(floor(F / s_F + 0.5), 1)``. With the defaults the median
        image has 2-3 flares.
    flare_count : (int, int)
        Clip range of ``N_F`` (the paper's [1, 20]); ``(3, 3)`` forces three flares.
    flare_max_depth : float, metres
        Light sources sit at pixels with depth in (0, flare_max_depth] when a depth map is given.
    ghosts : bool
        Add ghost reflections along the line through the image centre.
    noise : {"eld", "gaussian", "none"}
        ELD (Tukey-lambda read noise), the same with Gaussian read noise (ELD's separate
        Gaussian fit of the read-noise scale), or no noise.
    camera : str
        ELD camera table: SonyA7S2, NikonD850, CanonEOS70D, CanonEOS700D, CanonEOS5D4, or
        "random" (one per image).
    ratio : (float, float)
        Exposure ratio ``~ logU``: the linear image in [0, 1] spans ``saturation / ratio`` DN.
        2-32 gives visible night-street noise; ELD's extreme low light is 100-300.
    bank_seed, bank_count, bank_size : int
        Flare bank (see :func:`sparsetools.ops.flare.flare_bank`).
    color_bias : bool
        Add the camera table's per-channel black-level offsets (ELD ``color_bias``) of the
        drawn calibration row; off by default.
    """

    brightness: tuple[float, float] = (0.4, 1.0)
    gamma: tuple[float, float] = (1.8, 2.2)
    flare: bool = True
    flare_scale: tuple[float, float] = (0.2, 1.0)
    flare_amount: tuple[float, float] = (0.3, 3.0)
    flare_count: tuple[int, int] = (1, 20)
    flare_max_depth: float = 20.0
    ghosts: bool = True
    noise: str = "eld"
    camera: str = "SonyA7S2"
    ratio: tuple[float, float] = (2.0, 32.0)
    bank_seed: int = 0
    bank_count: int = 16
    bank_size: int = 256
    color_bias: bool = False

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise the tuples once
        # (low, high) ranges with low > 0; the upper bounds keep the draws in float range.
        highs = {"brightness": 10.0, "gamma": 10.0, "flare_scale": 10.0, "flare_amount": 1e4,
                 "ratio": 1e6}  # fmt: skip
        for name, high in highs.items():
            pair = check_pair(getattr(self, name), name, low=0.0, strict=True, high=high)
            set_(self, name, pair)
        count = check_pair(self.flare_count, "flare_count", low=1, high=1000, integer=True)
        set_(self, "flare_count", count)
        check_positive(self.flare_max_depth, "flare_max_depth")
        check_flag(self.color_bias, "color_bias")
        check_choice(self.noise, "noise", NOISE_MODELS)
        check_choice(self.camera, "camera", (*CAMERA_PROFILES, "random"))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class LowLightRecord:
    """Every value sampled for one night image; ``to_dict()`` is JSON-serialisable.

    Attributes
    ----------
    height, width : int
        Image size the record was drawn for.
    brightness : float
        ``s_b``.
    gamma : float
        ``g``.
    flare_source : str
        "depth" (sources at pixels with depth in (0, max] m), "uniform" (no depth given),
        "depth-none-in-range" (depth given but no eligible pixel: no flare) or "off".
    flare_scale, flare_amount : float
        ``s_F`` and ``F`` (0 when flares are off).
    flare_count : int
        ``N_F``.
    flares : list of FlareRecord
        Centre, 3-D point, size, pattern id, rotation, intensity, colour and ghosts of each.
    bank_seed, bank_count, bank_size, bank_version : int
        Which flare bank the pattern ids refer to.
    noise : NoiseParams
        Camera, gain ``K``, ratio, Tukey lambda (and its table row), read and row sigmas,
        colour bias and the noise seed. Records written before the camera tables were used
        lack ``color_bias`` / ``table_row`` and replay exactly as before.
    version : int
        Record layout version.
    """

    height: int
    width: int
    brightness: float
    gamma: float
    flare_source: str
    flare_scale: float
    flare_amount: float
    flare_count: int
    flares: list[FlareRecord]
    bank_seed: int
    bank_count: int
    bank_size: int
    bank_version: int
    noise: NoiseParams
    version: int = RECORD_VERSION
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["flares"] = [f.to_dict() for f in self.flares]
        d["noise"] = self.noise.to_dict()
        d["extra"] = dict(self.extra)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> LowLightRecord:
        if not isinstance(d, dict):
            raise ParameterError(f"not a valid low-light record (a {type(d).__name__})")
        try:
            version = int(d.get("version", RECORD_VERSION))
            if version != RECORD_VERSION:
                raise ParameterError(
                    f"record version {version} is not supported (expected {RECORD_VERSION})"
                )
            return cls(
                height=int(d["height"]), width=int(d["width"]),
                brightness=float(d["brightness"]), gamma=float(d["gamma"]),
                flare_source=str(d["flare_source"]), flare_scale=float(d["flare_scale"]),
                flare_amount=float(d["flare_amount"]), flare_count=int(d["flare_count"]),
                flares=[FlareRecord.from_dict(f) for f in d["flares"]],
                bank_seed=int(d["bank_seed"]), bank_count=int(d["bank_count"]),
                bank_size=int(d["bank_size"]), bank_version=int(d["bank_version"]),
                noise=NoiseParams.from_dict(d["noise"]), version=version,
                extra=dict(d.get("extra", {})),
            )  # fmt: skip
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            if isinstance(exc, ParameterError):
                raise
            raise ParameterError(
                f"not a valid low-light record ({type(exc).__name__}: {exc})"
            ) from exc

    @classmethod
    def from_json(cls, text: str) -> LowLightRecord:
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise ParameterError(f"low-light record is not valid JSON ({exc})") from exc

    def summary(self) -> dict:
        """Flat scalar (and list) columns for a manifest row."""
        n = self.noise
        return {
            "brightness": self.brightness, "gamma": self.gamma,
            "flare_source": self.flare_source, "flare_scale": self.flare_scale,
            "flare_amount": self.flare_amount, "flare_count": self.flare_count,
            "flare_u": [f.u for f in self.flares], "flare_v": [f.v for f in self.flares],
            "flare_depth": [f.depth for f in self.flares],
            "flare_pattern": [f.pattern for f in self.flares],
            "noise_model": n.model, "camera": n.camera, "system_gain": n.system_gain,
            "ratio": n.ratio, "saturation": n.saturation, "tukey_lambda": n.tukey_lambda,
            "sigma_read": n.sigma_read, "sigma_row": n.sigma_row, "noise_seed": n.seed,
            "color_bias": list(n.color_bias), "noise_table_row": n.table_row,
        }  # fmt: skip


def _check_image(image: np.ndarray) -> np.ndarray:
    """An (H, W, 3) uint8 RGB image; the two likely mistakes (16-bit, grey) say what to do."""
    check_array(image, "image")
    if image.dtype == np.uint16:
        raise ParameterError(
            "is 16-bit (uint16): scale it to 8 bits first, e.g. image >> 8", param="image"
        )
    check_dtype(image, "image", (np.uint8,))
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        raise ParameterError(
            f"is a grey image of shape {image.shape}: replicate it to three channels (H, W, 3), "
            "as sparsetools.read_image does",
            param="image",
        )
    check_shape(image, "(H, W, 3)", "image", nonempty=True)
    return image


def _check_depth(depth, shape: tuple[int, int]) -> np.ndarray | None:
    if depth is None:
        return None
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    check_shape(d, "({}, {})".format(*shape), "depth")  # the image's size
    check_dtype(d, "depth", "fiu")
    return d


def _check_intrinsics(K) -> np.ndarray | None:
    if K is None:
        return None
    K = np.asarray(K, dtype=np.float64)
    if K.shape == (3, 4):
        K = K[:, :3]
    check_shape(K, "(3, 3)", "K")
    check_all_finite(K, "K")
    if abs(np.linalg.det(K)) < 1e-12:
        raise ParameterError("intrinsics K is singular", param="K")
    return K


def _as_generator(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None:
        raise ParameterError("lowlight needs rng (a numpy Generator or an int seed) or a record")
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise ParameterError(
        f"rng must be a numpy.random.Generator or an int seed, got {type(rng).__name__}"
    )


def _sample(
    rng: np.random.Generator,
    height: int,
    width: int,
    params: LowLightParams,
    depth: np.ndarray | None,
    K: np.ndarray | None,
    bank: FlareBank | None,
) -> LowLightRecord:
    # Three independent streams: switching flares or noise off leaves the other draws unchanged.
    seeds = rng.integers(0, 2**63 - 1, size=3)
    base, flare_rng, noise_rng = (np.random.default_rng(int(s)) for s in seeds)
    s_b = float(base.uniform(*params.brightness))
    gamma = float(base.uniform(*params.gamma))
    if params.flare:
        drawn = sample_flares(
            flare_rng,
            height,
            width,
            bank=bank,
            scale_range=params.flare_scale,
            amount_range=params.flare_amount,
            count_range=params.flare_count,
            depth=depth,
            intrinsics=K,
            max_depth=params.flare_max_depth,
            ghosts=params.ghosts,
        )
    else:
        drawn = {"source": "off", "scale": 0.0, "amount": 0.0, "count": 0, "flares": []}
    noise = sample_noise_params(noise_rng, camera=params.camera, model=params.noise,
                                ratio_range=params.ratio, color_bias=params.color_bias)  # fmt: skip
    return LowLightRecord(
        height=height, width=width, brightness=s_b, gamma=gamma,
        flare_source=drawn["source"], flare_scale=drawn["scale"], flare_amount=drawn["amount"],
        flare_count=drawn["count"], flares=drawn["flares"], bank_seed=params.bank_seed,
        bank_count=params.bank_count, bank_size=params.bank_size, bank_version=BANK_VERSION,
        noise=noise,
    )  # fmt: skip


def _compose(image: np.ndarray, record: LowLightRecord, bank: FlareBank | None) -> np.ndarray:
    s_b, g = record.brightness, record.gamma
    check_positive(s_b, "brightness")
    check_positive(g, "gamma")
    # (s_b I)^g through a 256-entry table: exact and far cheaper than a per-pixel power.
    lut = (s_b * np.arange(256, dtype=np.float64) / 255.0) ** g
    linear = lut[image]
    if record.flares:
        linear += render_flares(record.height, record.width, record.flares, bank=bank, gamma=g)
    n = record.noise
    if n.model != "none":
        to_raw = n.saturation / n.ratio
        linear *= to_raw
        linear = add_sensor_noise(linear, n)
        linear *= 1.0 / to_raw
    np.clip(linear, 0.0, 1.0, out=linear)
    out = np.power(linear, 1.0 / g, out=linear)
    out *= 255.0
    return np.rint(out).astype(np.uint8)


def lowlight(
    image: np.ndarray,
    *,
    depth: np.ndarray | None = None,
    K: np.ndarray | None = None,
    rng: np.random.Generator | int | None = None,
    params: LowLightParams | None = None,
    record: LowLightRecord | dict | None = None,
    bank: FlareBank | None = None,
) -> tuple[np.ndarray, LowLightRecord]:
    """Turn a day image into a synthetic night image (flares + ELD sensor noise).

    Parameters
    ----------
    image : (H, W, 3) uint8
        RGB day image. Grey or 16-bit images are refused (convert them first).
    depth : (H, W) float, metres, optional
        Paired depth (0 or non-finite = none). Flare light sources are placed only at pixels
        with depth in (0, ``params.flare_max_depth``]; without it they are uniform.
    K : (3, 3) float, optional
        Camera intrinsics; with ``depth`` each light source's 3-D point
        ``P = z K^-1 [u v 1]^T`` is recorded.
    rng : numpy.random.Generator or int
        Source of every random draw (ignored when ``record`` is given).
    params : LowLightParams, optional
        Sampling ranges (defaults: METHODS.md section 4).
    record : LowLightRecord or dict, optional
        Replay: use these values instead of sampling; the output is identical to the run
        that produced the record.
    bank : FlareBank, optional
        Flare patterns; default the bank named by ``params`` (or the record), built once per
        process (:func:`~sparsetools.ops.flare.flare_bank`).

    Returns
    -------
    night : (H, W, 3) uint8
        RGB night image.
    record : LowLightRecord
        Every sampled value (``record.to_dict()`` is JSON-serialisable).

    Examples
    --------
    >>> night, rec = lowlight(day, depth=depth, K=calib.K, rng=np.random.default_rng(0))
    >>> again, _ = lowlight(day, record=rec.to_dict())   # identical to ``night``
    """
    image = _check_image(image)
    h, w = image.shape[:2]
    depth = _check_depth(depth, (h, w))
    K = _check_intrinsics(K)
    if record is not None:
        check_instance(record, "record", (LowLightRecord, dict))
        if isinstance(record, dict):
            record = LowLightRecord.from_dict(record)
        if (record.height, record.width) != (h, w):
            raise ParameterError(
                f"record was drawn for a {record.width}x{record.height} image, got {w}x{h}"
            )
        if record.bank_version != BANK_VERSION:
            raise ParameterError(
                f"record uses flare bank version {record.bank_version}, this sparsetools "
                f"builds version {BANK_VERSION}: the flares cannot be reproduced"
            )
    else:
        params = params or LowLightParams()
        gen = _as_generator(rng)
    if record is not None:
        bank_key = (record.bank_seed, record.bank_count, record.bank_size)
        need_bank = bool(record.flares)
    else:
        bank_key = (params.bank_seed, params.bank_count, params.bank_size)
        need_bank = params.flare
    if need_bank:
        if bank is None:
            bank = flare_bank(seed=bank_key[0], count=bank_key[1], size=bank_key[2])
        elif (bank.seed, bank.count, bank.size) != bank_key:
            raise ParameterError(
                f"flare bank (seed {bank.seed}, {bank.count} patterns of {bank.size} px) does not "
                f"match the requested one (seed {bank_key[0]}, {bank_key[1]} of {bank_key[2]} px)"
            )
    if record is None:
        record = _sample(gen, h, w, params, depth, K, bank)
    return _compose(image, record, bank), record
