"""Sensor noise after the ELD physics-based model (Wei et al., CVPR 2020).

The model works in linear raw-like units (digital numbers after black-level subtraction):

    z = K * Poisson(x / K) + N_read + N_row + N_q (+ b_c)

- shot noise: photo-electron counts ``x / K`` are Poisson, ``K`` the system gain (DN per e-),
  with ``log K ~ U(log K_min, log K_max)``;
- read noise: Tukey-lambda with shape ``lambda`` and scale ``sigma_read``,
  ``log sigma_read ~ N(slope * log K + bias, sigma)`` with the camera's Tukey-lambda fit
  (``G_scale``), or Gaussian with the camera's separate Gaussian fit (``g_scale``);
- row noise: one ``N(0, sigma_row)`` offset per image row (shared by its columns and colour
  channels, as a banding offset in the read-out electronics would be),
  ``log sigma_row ~ N(slope * log K + bias, sigma)`` (``R_scale``);
- quantisation: ``U(-0.5, 0.5)`` (one DN step);
- optional per-channel black-level offset ``b_c`` (``color_bias``), off by default.

The camera tables are ELD's released calibrations (``sparsetools/data/eld_cameras.json``, MIT,
Wei et al. CVPR 2020; METHODS.md section 4). Each table holds a discrete list of fitted
Tukey-lambda shapes and, row for row, colour-bias offsets; a draw picks one row uniformly.
``saturation`` (white minus black level) only sets the raw scale at which a [0, 1] linear
image is expressed (``x = I * saturation / ratio``).

Tables reach this module two ways: the package's own file, read once by
:func:`_builtin_profiles` (the only file this module opens), or a :class:`CameraProfile`
passed as ``camera=`` (for instance from :func:`sparsetools.io.camera_tables.read_camera_tables`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from types import MappingProxyType

import numpy as np

from ..errors import FormatError, ParameterError
from ..validate import (
    check_all_finite,
    check_choice,
    check_int_range,
    check_non_negative,
    check_pair,
    check_positive,
    check_range,
    check_shape,
    check_values,
)

__all__ = [
    "CAMERA_PROFILES",
    "CameraProfile",
    "NoiseParams",
    "add_sensor_noise",
    "camera_profile",
    "noise_variance",
    "sample_noise_params",
]


@dataclass(frozen=True)
class CameraProfile:
    """One camera's ELD noise calibration.

    Attributes
    ----------
    name : str
    gain_range : (float, float)
        System gain ``K`` range (DN per electron), sampled log-uniformly (``Kmin``, ``Kmax``).
    read_slope, read_bias, read_sigma : float
        ``log sigma_read ~ N(read_slope * log K + read_bias, read_sigma)``, Tukey-lambda
        scale (ELD ``G_scale``).
    gaussian_slope, gaussian_bias, gaussian_sigma : float
        The same for the Gaussian read-noise model (ELD ``g_scale``, a separate fit).
    row_slope, row_bias, row_sigma : float
        ``log sigma_row ~ N(row_slope * log K + row_bias, row_sigma)`` (ELD ``R_scale``).
    tukey_lambdas : tuple of float
        The fitted Tukey-lambda shapes (ELD ``G_shape``), one per calibration row.
    color_bias : tuple of (float, float, float, float)
        Black-level offsets in DN per row, ELD's packed raw order (R, G1, B, G2); as many rows
        as ``tukey_lambdas``.
    saturation : float
        White level minus black level, DN.
    """

    name: str
    gain_range: tuple[float, float]
    read_slope: float
    read_bias: float
    read_sigma: float
    gaussian_slope: float
    gaussian_bias: float
    gaussian_sigma: float
    row_slope: float
    row_bias: float
    row_sigma: float
    tukey_lambdas: tuple[float, ...]
    color_bias: tuple[tuple[float, float, float, float], ...]
    saturation: float

    @property
    def lambda_range(self) -> tuple[float, float]:
        """Smallest and largest fitted Tukey-lambda shape."""
        return (min(self.tukey_lambdas), max(self.tukey_lambdas))

    def rgb_bias(self, row: int) -> tuple[float, float, float]:
        """Colour-bias offsets of one calibration row for an RGB image, DN.

        R and B are taken as they are; G is the mean of the two green sites.
        """
        r, g1, b, g2 = self.color_bias[row]
        return (float(r), 0.5 * (float(g1) + float(g2)), float(b))

    @classmethod
    def from_dict(cls, name: str, entry: Mapping, *, profile: str = "Profile-1") -> CameraProfile:
        """Profile from one camera entry of an ELD table (``Kmin``, ``Kmax``, ``G_shape``,
        ``color_bias``, ``Profile-1`` with ``G_scale`` / ``g_scale`` / ``R_scale``,
        ``saturation_dn``).

        Raises
        ------
        FormatError
            A key is missing, a value is not a finite number, or the row counts differ.
        """
        try:
            fits = entry[profile]
            tl, ga, row = fits["G_scale"], fits["g_scale"], fits["R_scale"]
            shapes = tuple(float(v) for v in entry["G_shape"])
            bias = tuple(tuple(float(v) for v in r) for r in entry["color_bias"])
            numbers = (float(entry["Kmin"]), float(entry["Kmax"]),
                       *(float(f[k]) for f in (tl, ga, row) for k in ("slope", "bias", "sigma")),
                       float(entry["saturation_dn"]))  # fmt: skip
        except (KeyError, TypeError, ValueError) as exc:
            raise FormatError(f"camera table '{name}': missing or bad value ({exc!r})") from exc
        if not all(math.isfinite(v) for v in (*numbers, *shapes, *sum(bias, ()))):
            raise FormatError(f"camera table '{name}': non-finite value")
        if not shapes or len(bias) != len(shapes) or any(len(r) != 4 for r in bias):
            raise FormatError(
                f"camera table '{name}': need as many color_bias rows of 4 (R, G1, B, G2) as "
                f"G_shape values, got {len(bias)} rows for {len(shapes)} shapes"
            )
        k_min, k_max, *scales, saturation = numbers
        if not (0 < k_min <= k_max) or not saturation > 0:
            raise FormatError(f"camera table '{name}': need 0 < Kmin <= Kmax and saturation > 0")
        return cls(name, (k_min, k_max), *scales[:3], *scales[3:6], *scales[6:9],
                   shapes, bias, saturation)  # fmt: skip


def _builtin_profiles() -> Mapping[str, CameraProfile]:
    """The ELD tables shipped with the package (:mod:`.eld_tables`, the values of
    ``sparsetools/data/eld_cameras.json``)."""
    from .eld_tables import ELD_CAMERAS

    cams = ELD_CAMERAS
    return MappingProxyType({n: CameraProfile.from_dict(n, cams[n]) for n in sorted(cams)})


#: ELD's released camera tables (read-only), by name: CanonEOS5D4, CanonEOS700D, CanonEOS70D,
#: NikonD850, SonyA7S2.
CAMERA_PROFILES: Mapping[str, CameraProfile] = _builtin_profiles()

NOISE_MODELS = ("eld", "gaussian", "none")


@dataclass(frozen=True)
class NoiseParams:
    """Every sampled value of one noise draw (enough to regenerate it exactly).

    Attributes
    ----------
    model : {"eld", "gaussian", "none"}
        Read-noise distribution: Tukey-lambda (ELD) or Gaussian; "none" adds nothing.
    camera : str
    system_gain : float
        ``K``, DN per electron.
    ratio : float
        Exposure ratio: the linear image in [0, 1] maps to ``saturation / ratio`` DN.
    saturation : float
        DN of a linear value of 1 at ratio 1.
    tukey_lambda : float
        Read-noise shape (unused for the Gaussian model).
    sigma_read, sigma_row : float
        Scales in DN.
    seed : int
        Seed of the generator that draws the noise itself.
    color_bias : (float, float, float)
        Black-level offset added to the R, G, B channels, DN (zeros unless asked for; a 2-D
        image gets their mean).
    table_row : int
        Calibration row of the camera table that gave ``tukey_lambda`` (and ``color_bias``);
        -1 in records made before the tables were used (lambda then drawn uniformly).
    """

    model: str
    camera: str
    system_gain: float
    ratio: float
    saturation: float
    tukey_lambda: float
    sigma_read: float
    sigma_row: float
    seed: int
    color_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    table_row: int = -1

    def __post_init__(self) -> None:
        # A list (e.g. from NoiseParams(**d)) would make the record unhashable and unequal.
        object.__setattr__(self, "color_bias", tuple(float(v) for v in self.color_bias))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["color_bias"] = list(self.color_bias)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> NoiseParams:
        """Parse :meth:`to_dict` output; records without ``color_bias`` / ``table_row``
        (written before they existed) get no bias and row -1, and replay as before."""
        bias = tuple(float(v) for v in d.get("color_bias", (0.0, 0.0, 0.0)))
        if len(bias) != 3:
            raise ParameterError(f"noise color_bias must hold 3 values (R, G, B), got {bias}")
        return cls(
            model=str(d["model"]),
            camera=str(d["camera"]),
            system_gain=float(d["system_gain"]),
            ratio=float(d["ratio"]),
            saturation=float(d["saturation"]),
            tukey_lambda=float(d["tukey_lambda"]),
            sigma_read=float(d["sigma_read"]),
            sigma_row=float(d["sigma_row"]),
            seed=int(d["seed"]),
            color_bias=bias,
            table_row=int(d.get("table_row", -1)),
        )


def camera_profile(name: str) -> CameraProfile:
    """Profile by name (:data:`CAMERA_PROFILES`), with a clear error for unknown names."""
    return CAMERA_PROFILES[check_choice(name, "camera", CAMERA_PROFILES)]


def sample_noise_params(
    rng: np.random.Generator,
    *,
    camera: str | CameraProfile = "SonyA7S2",
    model: str = "eld",
    ratio_range: tuple[float, float] = (1.0, 8.0),
    color_bias: bool = False,
) -> NoiseParams:
    """Draw one set of noise parameters from a camera table.

    Parameters
    ----------
    rng : numpy.random.Generator
    camera : str or CameraProfile
        A key of :data:`CAMERA_PROFILES`, ``"random"`` to pick one of them uniformly, or a
        profile of one's own (e.g. read by :func:`sparsetools.io.camera_tables.read_camera_tables`).
    model : {"eld", "gaussian", "none"}
        "eld": Tukey-lambda read noise with the ``G_scale`` fit; "gaussian": Gaussian read
        noise with the ``g_scale`` fit.
    ratio_range : (float, float)
        Exposure ratio range, sampled log-uniformly; >= 1 darkens the raw signal and so
        raises the relative noise (ELD uses 100-300 for extreme low light).
    color_bias : bool
        Add the drawn calibration row's black-level offsets (``NoiseParams.color_bias``).

    Returns
    -------
    NoiseParams
        The draw order is fixed (camera, K, table row, sigma_read, sigma_row, ratio, seed)
        and does not depend on ``model`` or ``color_bias``, so switching them leaves the other
        values unchanged. The row picks ``tukey_lambda`` from the table's discrete shapes.
    """
    check_choice(model, "model", NOISE_MODELS)
    lo, hi = check_pair(ratio_range, "ratio_range", low=0.0, strict=True)
    if isinstance(camera, CameraProfile):
        prof = camera
    else:
        if camera == "random":
            names = sorted(CAMERA_PROFILES)
            camera = names[int(rng.integers(len(names)))]
        prof = camera_profile(camera)
    log_k = rng.uniform(math.log(prof.gain_range[0]), math.log(prof.gain_range[1]))
    row = int(rng.integers(len(prof.tukey_lambdas)))
    if model == "gaussian":
        slope, bias, sigma = prof.gaussian_slope, prof.gaussian_bias, prof.gaussian_sigma
    else:
        slope, bias, sigma = prof.read_slope, prof.read_bias, prof.read_sigma
    log_read = rng.normal(slope * log_k + bias, sigma)
    log_row = rng.normal(prof.row_slope * log_k + prof.row_bias, prof.row_sigma)
    ratio = math.exp(rng.uniform(math.log(lo), math.log(hi)))
    seed = int(rng.integers(0, 2**63 - 1))
    if model == "none":
        return NoiseParams("none", prof.name, 1.0, 1.0, prof.saturation, 0.0, 0.0, 0.0, seed)
    return NoiseParams(
        model=model,
        camera=prof.name,
        system_gain=float(math.exp(log_k)),
        ratio=float(ratio),
        saturation=prof.saturation,
        tukey_lambda=prof.tukey_lambdas[row],
        sigma_read=float(math.exp(log_read)),
        sigma_row=float(math.exp(log_row)),
        seed=seed,
        color_bias=prof.rgb_bias(row) if color_bias else (0.0, 0.0, 0.0),
        table_row=row,
    )


def _check_params(params: NoiseParams) -> None:
    """The fields of a record (perhaps read back from JSON), each named as the field."""
    check_choice(params.model, "model", NOISE_MODELS)
    check_int_range(params.seed, "seed", low=0, high=2**63 - 1)
    if params.model == "none":
        return
    for name in ("system_gain", "ratio", "saturation"):
        check_positive(getattr(params, name), name)
    for name in ("sigma_read", "sigma_row"):
        check_non_negative(getattr(params, name), name)
    bias = np.asarray(params.color_bias, dtype=np.float64)
    check_shape(bias, "(3)", "color_bias")  # R, G, B
    check_all_finite(bias, "color_bias")
    if params.model == "eld":
        # Outside (-1/2, 1) the read-noise variance is infinite or the support is tiny.
        check_range(params.tukey_lambda, "tukey_lambda", low=-0.5, high=1.0, low_open=True,
                    high_open=True)  # fmt: skip


def add_sensor_noise(raw: np.ndarray, params: NoiseParams) -> np.ndarray:
    """Add ELD noise to a clean image in raw units (DN).

    Parameters
    ----------
    raw : (H, W) or (H, W, C) float, DN >= 0
        Clean signal (expected value of each pixel).
    params : NoiseParams
        The noise itself is drawn from ``numpy.random.default_rng(params.seed)`` in a fixed
        order (shot, read, row, quantisation): the same parameters give the same noise. A
        non-zero ``color_bias`` is added last: per channel to (H, W, 3), its mean otherwise.

    Returns
    -------
    (H, W) or (H, W, C) float64
        Noisy signal in DN (may be negative: no clipping here).
    """
    _check_params(params)
    x = np.asarray(raw, dtype=np.float64)
    check_shape(x, "(H, W) | (H, W, C)", "raw")
    if params.model == "none":
        return x.copy()
    check_all_finite(x, "raw")
    check_values(x, "raw", low=0.0)  # DN
    from scipy import stats

    gen = np.random.default_rng(params.seed)
    k = params.system_gain
    z = gen.poisson(x / k).astype(np.float64)
    z *= k
    if params.model == "eld":
        read = stats.tukeylambda.rvs(
            params.tukey_lambda, scale=params.sigma_read, size=x.shape, random_state=gen
        )
    else:
        read = stats.norm.rvs(scale=params.sigma_read, size=x.shape, random_state=gen)
    z += read
    row = stats.norm.rvs(scale=params.sigma_row, size=x.shape[0], random_state=gen)
    z += row.reshape((-1,) + (1,) * (x.ndim - 1))
    z += stats.uniform.rvs(loc=-0.5, scale=1.0, size=x.shape, random_state=gen)
    if any(params.color_bias):
        # Added after the draws, so the noise itself is the same with or without the offsets.
        if x.ndim == 3 and x.shape[2] == 3:
            z += np.asarray(params.color_bias, dtype=np.float64)
        else:
            z += float(np.mean(params.color_bias))
    return z


def noise_variance(signal: np.ndarray | float, params: NoiseParams) -> np.ndarray:
    """Predicted per-pixel noise variance (DN^2) at a clean signal level (DN).

    ``K * x`` (shot) + read variance (Tukey-lambda or Gaussian) + ``sigma_row^2`` + 1/12.
    Useful to check a simulation or to weight a denoising loss. The colour bias shifts the
    mean, not the variance.
    """
    _check_params(params)
    x = np.asarray(signal, dtype=np.float64)
    if params.model == "none":
        return np.zeros_like(x)
    from scipy import stats

    if params.model == "eld":
        read_var = float(stats.tukeylambda.var(params.tukey_lambda)) * params.sigma_read**2
    else:
        read_var = params.sigma_read**2
    return params.system_gain * x + read_var + params.sigma_row**2 + 1.0 / 12.0
