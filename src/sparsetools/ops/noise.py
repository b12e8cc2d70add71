"""Sensor noise after the ELD physics-based model (Wei et al., CVPR 2020).

The model works in linear raw-like units (digital numbers after black-level subtraction):

    z = K * Poisson(x / K) + N_read + N_row + N_q

- shot noise: photo-electron counts ``x / K`` are Poisson, ``K`` the system gain (DN per e-),
  with ``log K ~ U(log K_min, log K_max)``;
- read noise: Tukey-lambda with shape ``lambda`` and scale ``sigma_read``,
  ``log sigma_read ~ N(slope * log K + bias, sigma)`` (or a Gaussian of the same scale);
- row noise: one ``N(0, sigma_row)`` offset per image row (shared by its columns and colour
  channels, as a banding offset in the read-out electronics would be),
  ``log sigma_row ~ N(slope * log K + bias, sigma)``;
- quantisation: ``U(-0.5, 0.5)`` (one DN step).

The camera profiles are the published ELD calibrations (METHODS.md section 4). The white
level minus black level (``saturation``) is the usual 14-bit range of each body; it only sets
the raw scale at which a [0, 1] linear image is expressed (``x = I * saturation / ratio``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..errors import ParameterError

__all__ = [
    "CAMERA_PROFILES",
    "CameraProfile",
    "NoiseParams",
    "add_sensor_noise",
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
        System gain ``K`` range (DN per electron), sampled log-uniformly.
    read_slope, read_bias, read_sigma : float
        ``log sigma_read ~ N(read_slope * log K + read_bias, read_sigma)`` (Tukey-lambda scale).
    row_slope, row_bias, row_sigma : float
        ``log sigma_row ~ N(row_slope * log K + row_bias, row_sigma)``.
    lambda_range : (float, float)
        Tukey-lambda shape range, sampled uniformly.
    saturation : float
        White level minus black level, DN (14-bit raw).
    """

    name: str
    gain_range: tuple[float, float]
    read_slope: float
    read_bias: float
    read_sigma: float
    row_slope: float
    row_bias: float
    row_sigma: float
    lambda_range: tuple[float, float]
    saturation: float


#: Published ELD profiles (K range; TL slope, bias, sigma; row slope, bias, sigma; lambda).
CAMERA_PROFILES: dict[str, CameraProfile] = {
    p.name: p
    for p in (
        CameraProfile("SonyA7S2", (0.0939, 6.011), 0.4621, 0.5657, 0.2634,
                      0.5275, -0.5917, 0.2943, (-0.143, 0.129), 16383.0 - 512.0),
        CameraProfile("NikonD850", (0.415, 26.56), 0.4774, -0.0904, 0.2392,
                      0.4483, -1.7977, 0.2322, (-0.243, -0.100), 16383.0 - 600.0),
        CameraProfile("CanonEOS70D", (0.407, 26.08), 0.4868, 1.4643, 0.3820,
                      0.7292, -0.9371, 0.2502, (-0.171, 0.143), 15000.0 - 2048.0),
    )
}  # fmt: skip

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

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> NoiseParams:
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
        )


def camera_profile(name: str) -> CameraProfile:
    """Profile by name (:data:`CAMERA_PROFILES`), with a clear error for unknown names."""
    try:
        return CAMERA_PROFILES[name]
    except KeyError:
        raise ParameterError(
            f"unknown camera '{name}' (choose {', '.join(CAMERA_PROFILES)})"
        ) from None


def sample_noise_params(
    rng: np.random.Generator,
    *,
    camera: str = "SonyA7S2",
    model: str = "eld",
    ratio_range: tuple[float, float] = (1.0, 8.0),
) -> NoiseParams:
    """Draw one set of noise parameters from a camera profile.

    Parameters
    ----------
    rng : numpy.random.Generator
    camera : str
        A key of :data:`CAMERA_PROFILES`, or ``"random"`` to pick one uniformly.
    model : {"eld", "gaussian", "none"}
    ratio_range : (float, float)
        Exposure ratio range, sampled log-uniformly; >= 1 darkens the raw signal and so
        raises the relative noise (ELD uses 100-300 for extreme low light).

    Returns
    -------
    NoiseParams
        The draw order is fixed (camera, K, lambda, sigma_read, sigma_row, ratio, seed), so a
        given generator state always gives the same parameters.
    """
    if model not in NOISE_MODELS:
        raise ParameterError(f"unknown noise model '{model}' (choose {', '.join(NOISE_MODELS)})")
    lo, hi = ratio_range
    if not (0 < lo <= hi) or not math.isfinite(hi):
        raise ParameterError(f"ratio range must satisfy 0 < low <= high, got {ratio_range}")
    if camera == "random":
        names = sorted(CAMERA_PROFILES)
        camera = names[int(rng.integers(len(names)))]
    prof = camera_profile(camera)
    log_k = rng.uniform(math.log(prof.gain_range[0]), math.log(prof.gain_range[1]))
    lam = rng.uniform(*prof.lambda_range)
    log_read = rng.normal(prof.read_slope * log_k + prof.read_bias, prof.read_sigma)
    log_row = rng.normal(prof.row_slope * log_k + prof.row_bias, prof.row_sigma)
    ratio = math.exp(rng.uniform(math.log(lo), math.log(hi)))
    seed = int(rng.integers(0, 2**63 - 1))
    if model == "none":
        return NoiseParams("none", camera, 1.0, 1.0, prof.saturation, 0.0, 0.0, 0.0, seed)
    return NoiseParams(
        model=model,
        camera=camera,
        system_gain=float(math.exp(log_k)),
        ratio=float(ratio),
        saturation=prof.saturation,
        tukey_lambda=float(lam),
        sigma_read=float(math.exp(log_read)),
        sigma_row=float(math.exp(log_row)),
        seed=seed,
    )


def _check_params(params: NoiseParams) -> None:
    if params.model not in NOISE_MODELS:
        raise ParameterError(f"unknown noise model '{params.model}'")
    if not 0 <= params.seed < 2**63:
        raise ParameterError(f"noise seed must be in [0, 2^63), got {params.seed}")
    if params.model == "none":
        return
    for name in ("system_gain", "ratio", "saturation"):
        v = getattr(params, name)
        if not (math.isfinite(v) and v > 0):
            raise ParameterError(f"noise {name} must be finite and > 0, got {v}")
    for name in ("sigma_read", "sigma_row"):
        v = getattr(params, name)
        if not (math.isfinite(v) and v >= 0):
            raise ParameterError(f"noise {name} must be finite and >= 0, got {v}")
    if params.model == "eld" and not (-0.5 < params.tukey_lambda < 1.0):
        # Outside (-1/2, 1) the read-noise variance is infinite or the support is tiny.
        raise ParameterError(f"Tukey lambda must be in (-0.5, 1), got {params.tukey_lambda}")


def add_sensor_noise(raw: np.ndarray, params: NoiseParams) -> np.ndarray:
    """Add ELD noise to a clean image in raw units (DN).

    Parameters
    ----------
    raw : (H, W) or (H, W, C) float, DN >= 0
        Clean signal (expected value of each pixel).
    params : NoiseParams
        The noise itself is drawn from ``numpy.random.default_rng(params.seed)`` in a fixed
        order (shot, read, row, quantisation): the same parameters give the same noise.

    Returns
    -------
    (H, W) or (H, W, C) float64
        Noisy signal in DN (may be negative: no clipping here).
    """
    _check_params(params)
    x = np.asarray(raw, dtype=np.float64)
    if x.ndim not in (2, 3):
        raise ParameterError(f"raw image must be (H, W) or (H, W, C), got shape {x.shape}")
    if params.model == "none":
        return x.copy()
    if not np.all(np.isfinite(x)) or (x.size and x.min() < 0):
        raise ParameterError("raw signal must be finite and >= 0")
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
    return z


def noise_variance(signal: np.ndarray | float, params: NoiseParams) -> np.ndarray:
    """Predicted per-pixel noise variance (DN^2) at a clean signal level (DN).

    ``K * x`` (shot) + read variance (Tukey-lambda or Gaussian) + ``sigma_row^2`` + 1/12.
    Useful to check a simulation or to weight a denoising loss.
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
