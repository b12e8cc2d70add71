"""Depth-dependent defocus blur from dense depth (DepthDark survey section 5, METHODS.md 11).

The thin-lens blur radius of "Dark Channel-Assisted Depth-from-Defocus from a Single Image"
(arXiv 2506.06643), in pixels:

    r(d) = 1 / (sqrt(2) p_x) * (A f / (D_fp - f)) * |d - D_fp| / d,     A = f / F_n

with ``f`` the focal length (m), ``F_n`` the f-number, ``A`` the aperture diameter (m),
``p_x`` the pixel pitch (m), ``D_fp`` the in-focus distance (m) and ``d`` the depth (m).
``r`` is used as the radius of a disk kernel (``kernel="disk"``, default) or as the standard
deviation of a Gaussian (``kernel="gaussian"``, the paper's ``G(x - y; r(d))``).

The image is rendered as depth layers (occlusion-aware): the signed radius
``c (1 - D_fp / d)`` (``c = r(inf)``, negative in front of the focal plane, increasing with
depth) is quantised in steps of ``layer_step`` pixels; each layer's premultiplied colour and
alpha are blurred with its kernel and the layers are composited far to near with "over"
(``C = C_k + (1 - a_k) C``), then divided by the accumulated alpha. A blurred near object so
spreads over the sharp background behind it, and no sharp background shows through its
blurred edge. Optional sensor noise (the ELD model of :mod:`.noise`) is added afterwards.
Every sampled value goes into a :class:`DefocusRecord`; ``defocus(..., record=r)`` replays it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from types import MappingProxyType

import numpy as np

from ..errors import ParameterError
from ..validate import (
    check_all_finite,
    check_array,
    check_choice,
    check_dtype,
    check_instance,
    check_non_negative,
    check_ordered,
    check_pair,
    check_positive,
    check_range,
    check_shape,
    check_values,
)
from .noise import CAMERA_PROFILES, NOISE_MODELS, NoiseParams, add_sensor_noise, sample_noise_params

__all__ = [
    "DEFOCUS_CAMERAS",
    "KERNELS",
    "RECORD_VERSION",
    "CameraOptics",
    "DefocusParams",
    "DefocusRecord",
    "blur_kernel",
    "blur_radius",
    "defocus",
]

#: Version of the record layout (stored in every record).
RECORD_VERSION = 1
KERNELS = ("disk", "gaussian")
MISSING_MODES = ("error", "far")


@dataclass(frozen=True)
class CameraOptics:
    """Lens and sensor of the blur model.

    Attributes
    ----------
    name : str
    focal_length_m : float
        Focal length ``f``, metres.
    f_number : float
        ``F_n``; the aperture diameter is ``A = f / F_n``.
    pixel_pitch_m : float
        ``p_x``, metres (centre-to-centre distance of the pixels of the image blurred).
    source : str
        Where the numbers come from.
    """

    name: str
    focal_length_m: float
    f_number: float
    pixel_pitch_m: float
    source: str = ""

    def __post_init__(self) -> None:
        for name in ("focal_length_m", "f_number", "pixel_pitch_m"):
            object.__setattr__(self, name, check_positive(getattr(self, name), name))

    @property
    def aperture_m(self) -> float:
        """Aperture diameter ``A = f / F_n``, metres."""
        return self.focal_length_m / self.f_number

    @classmethod
    def from_calibration(
        cls, focal_length_px: float, *, pixel_pitch_m: float, f_number: float, name: str = ""
    ) -> CameraOptics:
        """Optics from a calibrated focal length in pixels: ``f = f_px * p_x`` metres.

        Use the ``K[0, 0]`` of the images that are blurred (after any resize) together with
        the pitch of *those* pixels, so the blur is in the same pixels as the calibration.
        """
        f_px = check_positive(focal_length_px, "focal_length_px")
        p = check_positive(pixel_pitch_m, "pixel_pitch_m")
        label = name or f"calibration f={f_px:g} px"
        return cls(label, f_px * p, f_number, p, f"f = {f_px:g} px x {p:g} m (calibration)")


#: Camera presets with published focal length, f-number and pixel pitch.
DEFOCUS_CAMERAS: Mapping[str, CameraOptics] = MappingProxyType({
    c.name: c
    for c in (
        CameraOptics("dfd-nyu", 9e-3, 2.0, 7.5e-6,
                     "synthetic-defocus setting of arXiv 2506.06643 (DepthDark survey section 5): "
                     "f = 9 mm, F_n = 2, p_x = 7.5 um, with D_fp = 0.7 m"),
        CameraOptics("rpi-v1", 3.60e-3, 2.9, 1.4e-6,
                     "Raspberry Pi Camera Module v1 (OmniVision OV5647) hardware specification: "
                     "focal length 3.60 mm, F-stop 2.9, pixel size 1.4 um"),
        CameraOptics("rpi-v2", 3.04e-3, 2.0, 1.12e-6,
                     "Raspberry Pi Camera Module v2 (Sony IMX219) hardware specification "
                     "(raspberrypi/documentation): focal length 3.04 mm, F-stop 2.0, pixel "
                     "size 1.12 um"),
        CameraOptics("oak-ffc-imx378", 4.81e-3, 1.8, 1.55e-6,
                     "Luxonis OAK-FFC-IMX378 specification (docs.luxonis.com): effective focal "
                     "length 4.81 mm, F-number 1.8, pixel size 1.55 um"),
    )
})  # fmt: skip


def _optics(camera) -> CameraOptics:
    if isinstance(camera, CameraOptics):
        return camera
    if isinstance(camera, Mapping):  # DefocusParams.to_dict() round trip
        try:
            return CameraOptics(**camera)
        except TypeError as exc:
            raise ParameterError(f"not a valid camera description: {camera!r} ({exc})") from None
    return DEFOCUS_CAMERAS[check_choice(camera, "camera", DEFOCUS_CAMERAS)]


def _radius_scale(optics: CameraOptics, focus_distance_m: float, f_number: float) -> float:
    """``r(inf) = A f / ((D_fp - f) sqrt(2) p_x)``, pixels."""
    f = optics.focal_length_m
    check_ordered(f, focus_distance_m, "focal_length_m", "focus_distance_m")
    aperture = f / f_number
    return aperture * f / ((focus_distance_m - f) * math.sqrt(2.0) * optics.pixel_pitch_m)


def blur_radius(
    depth: np.ndarray,
    *,
    focus_distance_m: float,
    camera: str | CameraOptics = "dfd-nyu",
    f_number: float | None = None,
) -> np.ndarray:
    """Blur radius map ``r(d)`` in pixels.

    Parameters
    ----------
    depth : (H, W) float, metres
        Depth ``d`` (camera z). Non-finite or <= 0 entries are taken as infinitely far:
        ``r(inf) = A f / ((D_fp - f) sqrt(2) p_x)``.
    focus_distance_m : float
        In-focus distance ``D_fp``, metres (> f).
    camera : str or CameraOptics
        A key of :data:`DEFOCUS_CAMERAS` or explicit optics.
    f_number : float, optional
        Overrides the camera's f-number.

    Returns
    -------
    (H, W) float64, pixels
    """
    optics = _optics(camera)
    fn = optics.f_number if f_number is None else check_positive(f_number, "f_number")
    scale = _radius_scale(optics, check_positive(focus_distance_m, "focus_distance_m"), fn)
    s = _focus_offset(np.asarray(depth, dtype=np.float64), focus_distance_m)
    return scale * np.abs(s)


def _focus_offset(depth: np.ndarray, focus_distance_m: float) -> np.ndarray:
    """``(d - D_fp) / d``, and 1 (infinitely far) where there is no depth."""
    d = np.asarray(depth, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    out = np.ones_like(d)
    np.divide(d - focus_distance_m, d, out=out, where=valid)
    return out


def blur_kernel(radius: float, *, kernel: str = "disk") -> np.ndarray:
    """Normalised blur kernel of ``radius`` pixels.

    ``disk``: weight ``clip(radius + 1/2 - rho, 0, 1)`` at distance ``rho`` from the centre
    (a disk with a one-pixel linear edge, so the blur grows continuously with the radius;
    radius < 1/2 is the identity). ``gaussian``: ``exp(-rho^2 / (2 radius^2))`` out to
    3 radius (radius 0 is the identity).

    Returns
    -------
    (2 h + 1, 2 h + 1) float32, sums to 1
    """
    check_choice(kernel, "kernel", KERNELS)
    r = check_non_negative(radius, "radius")
    if r == 0:
        return np.ones((1, 1), np.float32)
    half = int(math.floor(r + 0.5)) if kernel == "disk" else int(math.ceil(3.0 * r))
    y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
    rho = np.hypot(x, y)
    if kernel == "disk":
        w = np.clip(r + 0.5 - rho, 0.0, 1.0)
    else:
        w = np.exp(-0.5 * (rho / r) ** 2)
    return (w / w.sum()).astype(np.float32)


@dataclass(frozen=True)
class DefocusParams:
    """Settings and sampling ranges of :func:`defocus`.

    Attributes
    ----------
    camera : str or CameraOptics
        A key of :data:`DEFOCUS_CAMERAS` (default ``dfd-nyu``, the paper's synthetic camera)
        or explicit optics (:meth:`CameraOptics.from_calibration` for f in pixels).
    focus_distance : (float, float) or float, metres
        ``D_fp ~ logU(low, high)``; equal bounds (or one number) fix it (default 0.7 m, the
        paper's).
    f_number : (float, float) or float, optional
        ``F_n ~ logU(low, high)``; default the camera's own.
    kernel : {"disk", "gaussian"}
    layer_step : float, pixels
        Quantisation step of the signed radius: each depth layer spans one step (the blur
        radius used is within ``layer_step / 2`` of ``r(d)``).
    max_radius : float, pixels
        Larger radii (very near or, with a short focus, very far pixels) are clipped.
    missing : {"error", "far"}
        Depth 0 / non-finite: refuse the image, or treat the pixel as infinitely far (sky).
    noise : {"none", "eld", "gaussian"}
        Sensor noise after the blur (ELD model).
    noise_camera : str
        ELD camera table for the noise.
    ratio : (float, float)
        Exposure ratio range of the noise (``~ logU``).
    noise_gamma : float
        The blurred image is linearised with this exponent before the noise, and re-encoded
        with its inverse.
    color_bias : bool
        Add the ELD table's black-level offsets with the noise.
    """

    camera: str | CameraOptics = "dfd-nyu"
    focus_distance: tuple[float, float] = (0.7, 0.7)
    f_number: tuple[float, float] | None = None
    kernel: str = "disk"
    layer_step: float = 0.5
    max_radius: float = 64.0
    missing: str = "error"
    noise: str = "none"
    noise_camera: str = "SonyA7S2"
    ratio: tuple[float, float] = (1.0, 8.0)
    noise_gamma: float = 2.2
    color_bias: bool = False

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise once
        set_(self, "camera", _optics(self.camera))
        # (low, high) ranges, low > 0; one number fixes the value
        set_(self, "focus_distance", check_pair(self.focus_distance, "focus_distance", low=0.0,
                                                strict=True))  # fmt: skip
        if self.f_number is not None:
            set_(self, "f_number", check_pair(self.f_number, "f_number", low=0.0, strict=True))
        set_(self, "ratio", check_pair(self.ratio, "ratio", low=0.0, strict=True))
        check_ordered(self.camera.focal_length_m, self.focus_distance[0], "focal_length_m",
                      "focus_distance")  # fmt: skip
        check_choice(self.kernel, "kernel", KERNELS)
        check_choice(self.missing, "missing", MISSING_MODES)
        check_choice(self.noise, "noise", NOISE_MODELS)
        check_choice(self.noise_camera, "noise_camera", (*CAMERA_PROFILES, "random"))
        set_(self, "max_radius", check_positive(self.max_radius, "max_radius"))
        # one layer spans layer_step pixels of radius: at most the whole range
        layer_step = check_range(self.layer_step, "layer_step", low=0.0, low_open=True,
                                 high=self.max_radius)  # fmt: skip
        set_(self, "layer_step", layer_step)
        set_(self, "noise_gamma", check_positive(self.noise_gamma, "noise_gamma"))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class DefocusRecord:
    """Every value used for one defocused image; ``to_dict()`` is JSON-serialisable.

    Attributes
    ----------
    height, width : int
    camera : str
        Name of the optics.
    focal_length_m, pixel_pitch_m : float
    f_number : float
        Sampled (or fixed) ``F_n``.
    focus_distance_m : float
        Sampled (or fixed) ``D_fp``.
    kernel : str
    layer_step, max_radius : float, pixels
    missing : str
    noise : NoiseParams
        Model "none" when no noise was added.
    noise_gamma : float
    version : int
    """

    height: int
    width: int
    camera: str
    focal_length_m: float
    pixel_pitch_m: float
    f_number: float
    focus_distance_m: float
    kernel: str
    layer_step: float
    max_radius: float
    missing: str
    noise: NoiseParams
    noise_gamma: float
    version: int = RECORD_VERSION

    @property
    def optics(self) -> CameraOptics:
        return CameraOptics(self.camera, self.focal_length_m, self.f_number, self.pixel_pitch_m)

    @property
    def radius_scale(self) -> float:
        """``r(inf)``, pixels."""
        return _radius_scale(self.optics, self.focus_distance_m, self.f_number)

    def to_dict(self) -> dict:
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["noise"] = self.noise.to_dict()
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: dict) -> DefocusRecord:
        if not isinstance(d, dict):
            raise ParameterError(f"not a valid defocus record (a {type(d).__name__})")
        try:
            version = int(d.get("version", RECORD_VERSION))
            if version != RECORD_VERSION:
                raise ParameterError(
                    f"defocus record version {version} is not supported ({RECORD_VERSION})"
                )
            rec = cls(
                height=int(d["height"]), width=int(d["width"]), camera=str(d["camera"]),
                focal_length_m=float(d["focal_length_m"]),
                pixel_pitch_m=float(d["pixel_pitch_m"]), f_number=float(d["f_number"]),
                focus_distance_m=float(d["focus_distance_m"]), kernel=str(d["kernel"]),
                layer_step=float(d["layer_step"]), max_radius=float(d["max_radius"]),
                missing=str(d["missing"]), noise=NoiseParams.from_dict(d["noise"]),
                noise_gamma=float(d["noise_gamma"]), version=version,
            )  # fmt: skip
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            if isinstance(exc, ParameterError):
                raise
            raise ParameterError(
                f"not a valid defocus record ({type(exc).__name__}: {exc})"
            ) from exc
        rec._check()
        return rec

    @classmethod
    def from_json(cls, text: str) -> DefocusRecord:
        try:
            return cls.from_dict(json.loads(text))
        except json.JSONDecodeError as exc:
            raise ParameterError(f"defocus record is not valid JSON ({exc})") from exc

    def _check(self) -> None:
        self.optics  # noqa: B018 (validates focal length, f-number and pitch)
        _radius_scale(self.optics, check_positive(self.focus_distance_m, "focus_distance_m"),
                      self.f_number)  # fmt: skip
        check_choice(self.kernel, "kernel", KERNELS)
        check_choice(self.missing, "missing", MISSING_MODES)
        for name in ("layer_step", "max_radius", "noise_gamma"):
            check_positive(getattr(self, name), name)


def _check_inputs(image, depth) -> tuple[np.ndarray, np.ndarray]:
    check_array(image, "image")
    check_shape(image, "(H, W) | (H, W, 1) | (H, W, 3)", "image", nonempty=True)
    check_dtype(image, "image", (np.uint8, np.float32, np.float64))
    if image.dtype == np.uint8:
        img = image.astype(np.float32) / np.float32(255.0)
    else:
        img = image.astype(np.float32)
        check_all_finite(img, "image")
        check_values(img, "image", low=0.0, high=1.0)
    d = np.asarray(depth)
    if d.ndim == 3 and d.shape[2] == 1:
        d = d[:, :, 0]
    check_shape(d, "({}, {})".format(*image.shape[:2]), "depth")  # the image's size
    check_dtype(d, "depth", "fiu")
    return (img if img.ndim == 3 else img[:, :, None]), d.astype(np.float64)


def _sample(rng, h: int, w: int, params: DefocusParams) -> DefocusRecord:
    optics = params.camera
    f_lo, f_hi = params.f_number or (optics.f_number, optics.f_number)
    d_lo, d_hi = params.focus_distance
    random = d_lo != d_hi or f_lo != f_hi or params.noise != "none"
    if rng is None and random:
        raise ParameterError("defocus samples values here: give rng (a Generator or an int seed)")
    if rng is None:
        u_focus = u_fn = 0.0
        noise = NoiseParams("none", params.noise_camera, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0)
    else:
        gen = _as_generator(rng)
        # Two independent streams: turning noise on or off leaves the optics draws unchanged.
        base_seed, noise_seed = (int(s) for s in gen.integers(0, 2**63 - 1, size=2))
        base = np.random.default_rng(base_seed)
        u_focus, u_fn = float(base.random()), float(base.random())
        noise = sample_noise_params(np.random.default_rng(noise_seed), camera=params.noise_camera,
                                    model=params.noise, ratio_range=params.ratio,
                                    color_bias=params.color_bias)  # fmt: skip
    return DefocusRecord(
        height=h, width=w, camera=optics.name, focal_length_m=optics.focal_length_m,
        pixel_pitch_m=optics.pixel_pitch_m, f_number=_log_uniform(f_lo, f_hi, u_fn),
        focus_distance_m=_log_uniform(d_lo, d_hi, u_focus), kernel=params.kernel,
        layer_step=params.layer_step, max_radius=params.max_radius, missing=params.missing,
        noise=noise, noise_gamma=params.noise_gamma,
    )  # fmt: skip


def _log_uniform(lo: float, hi: float, u: float) -> float:
    if lo == hi:
        return lo  # exactly the fixed value, not exp(log(lo)) one ulp away
    return math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))


def _as_generator(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        return np.random.default_rng(int(rng))
    raise ParameterError(
        f"rng must be a numpy.random.Generator or an int seed, got {type(rng).__name__}"
    )


def _composite(img: np.ndarray, layer: np.ndarray, record: DefocusRecord) -> np.ndarray:
    """Blur each layer's premultiplied colour and alpha with its kernel, "over" far to near."""
    import cv2

    h, w, c = img.shape
    acc = np.zeros((h, w, c + 1), np.float32)
    keys = np.unique(layer)
    for k in keys[::-1]:  # larger signed radius = farther
        mask = layer == k
        rows = np.flatnonzero(mask.any(axis=1))
        cols = np.flatnonzero(mask.any(axis=0))
        kern = blur_kernel(abs(int(k)) * record.layer_step, kernel=record.kernel)
        half = kern.shape[0] // 2
        # Crop with a margin of two kernel halves: the zeros in the outer half make the
        # reflecting border of the crop equal the full image's result.
        r0, r1 = max(rows[0] - 2 * half, 0), min(rows[-1] + 2 * half + 1, h)
        c0, c1 = max(cols[0] - 2 * half, 0), min(cols[-1] + 2 * half + 1, w)
        m = mask[r0:r1, c0:c1].astype(np.float32)
        src = np.concatenate([img[r0:r1, c0:c1] * m[:, :, None], m[:, :, None]], axis=2)
        if half:
            src = cv2.filter2D(src, -1, kern, borderType=cv2.BORDER_REFLECT)
            src = src.reshape(r1 - r0, c1 - c0, c + 1)
        view = acc[r0:r1, c0:c1]
        view *= 1.0 - src[:, :, c:]
        view += src
    alpha = acc[:, :, c:]
    return acc[:, :, :c] / np.maximum(alpha, np.float32(1e-12))


def defocus(
    image: np.ndarray,
    depth: np.ndarray,
    *,
    rng: np.random.Generator | int | None = None,
    params: DefocusParams | None = None,
    record: DefocusRecord | dict | None = None,
) -> tuple[np.ndarray, np.ndarray, DefocusRecord]:
    """Blur an image as a thin lens focused at ``D_fp`` would see it, from its dense depth.

    Parameters
    ----------
    image : (H, W, 3), (H, W, 1) or (H, W) uint8, or float in [0, 1]
        Sharp (all-in-focus) image.
    depth : (H, W) float, metres
        Dense depth of every pixel. Holes (0, non-finite) are refused unless
        ``params.missing == "far"``.
    rng : numpy.random.Generator or int, optional
        Needed when something is sampled (a focus or f-number range, noise).
    params : DefocusParams, optional
    record : DefocusRecord or dict, optional
        Replay: the output is identical to the run that produced the record.

    Returns
    -------
    blurred : same shape as ``image``; uint8 for uint8 input, else float32 in [0, 1]
    radius : (H, W) float32, pixels
        ``r(d)`` of every pixel (unquantised, unclipped; ``r(inf)`` where depth is missing).
    record : DefocusRecord

    Examples
    --------
    >>> params = DefocusParams(camera="dfd-nyu", focus_distance=(0.5, 2.0))
    >>> blurred, radius, rec = defocus(rgb, depth, rng=0, params=params)
    >>> again, _, _ = defocus(rgb, depth, record=rec.to_dict())   # identical
    """
    img, d = _check_inputs(image, depth)
    h, w = d.shape
    if record is not None:
        check_instance(record, "record", (DefocusRecord, dict))
        if isinstance(record, dict):
            record = DefocusRecord.from_dict(record)
        else:
            record._check()
        if (record.height, record.width) != (h, w):
            raise ParameterError(
                f"record was drawn for a {record.width}x{record.height} image, got {w}x{h}"
            )
    else:
        record = _sample(rng, h, w, params or DefocusParams())
    holes = ~(np.isfinite(d) & (d > 0))
    n_holes = int(np.count_nonzero(holes))
    if n_holes and record.missing == "error":
        raise ParameterError(
            f"depth is missing (0 or non-finite) at {n_holes} of {h * w} pixels: fill the holes "
            "or treat them as far (missing='far')"
        )
    offset = _focus_offset(d, record.focus_distance_m)
    scale = record.radius_scale
    signed = scale * offset
    k_max = int(math.floor(record.max_radius / record.layer_step))
    layer = np.clip(np.rint(signed / record.layer_step), -k_max, k_max).astype(np.int64)
    out = _composite(img, layer, record)
    n = record.noise
    if n.model != "none":
        g = record.noise_gamma
        to_raw = n.saturation / n.ratio
        linear = np.power(np.clip(out.astype(np.float64), 0.0, 1.0), g) * to_raw
        linear = add_sensor_noise(linear, n) / to_raw
        out = np.power(np.clip(linear, 0.0, 1.0), 1.0 / g)
    out = np.clip(out, 0.0, 1.0).reshape(image.shape)
    if image.dtype == np.uint8:
        out = np.rint(out * 255.0).astype(np.uint8)
    else:
        out = out.astype(np.float32)
    return out, np.abs(signed).astype(np.float32), record
