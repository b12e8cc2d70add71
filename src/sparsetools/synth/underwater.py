"""Synthetic underwater sequence with exact ground truth for median compensation.

Image model (arXiv 2110.00480, ``I_c = A_s F + B``), per channel c, in [0, 1]::

    I_t(x) = A[c] * albedo(x + offset_t) * cone_t(x) + B(x) + noise,   stored as 8-bit

- ``albedo``: a seafloor mosaic (sand texture, rocks, pebbles), wider than the image; the
  camera drifts over it by ``drift_px`` columns per frame, so a pixel sees different seafloor
  in different frames (what makes a temporal median estimate the lighting, not the floor).
- ``cone_t``: the lamp's light cone, a Gaussian spot ``floor + peak_t exp(-|x - c_t|^2 / 2 s^2)``
  whose centre ``c_t`` moves slowly across the image and whose peak flickers a little.
- ``A``: per-channel attenuation of the water column (red absorbed most).
- ``B``: additive backscatter, blue-green, brighter towards the top of the image.
- Water-only frames (``I = B + noise``) come first in time, as a vehicle descending would
  record them; they are given separately.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ParameterError

__all__ = ["UnderwaterSequence", "backscatter", "generate_underwater", "light_cone"]

STREAM_UNDERWATER = 9


def light_cone(
    height: int,
    width: int,
    *,
    centre: tuple[float, float],
    sigma: float,
    peak: float,
    floor: float,
) -> np.ndarray:
    """The lamp's light cone on the image.

    Parameters
    ----------
    height, width : int
        Image size, pixels.
    centre : (u, v) float, pixels
        Centre of the spot (0-based, pixel centres at integers).
    sigma : float, pixels
        Gaussian width of the spot.
    peak, floor : float
        Intensity at the centre is ``floor + peak``; far away it is ``floor``.

    Returns
    -------
    (H, W) float64
    """
    u = np.arange(width, dtype=np.float64) - centre[0]
    v = np.arange(height, dtype=np.float64) - centre[1]
    r2 = v[:, None] ** 2 + u[None, :] ** 2
    return floor + peak * np.exp(-r2 / (2.0 * sigma * sigma))


def backscatter(height: int, width: int, *, base, gradient: float) -> np.ndarray:
    """Additive backscatter ``B``: (H, W, 3) float64 in [0, 1].

    ``B(v) = base * (1 + gradient * (0.5 - v / (H - 1)))``: brighter at the top row.
    """
    v = np.arange(height, dtype=np.float64) / max(height - 1, 1)
    profile = 1.0 + gradient * (0.5 - v)
    b = profile[:, None, None] * np.asarray(base, dtype=np.float64)[None, None, :]
    return np.broadcast_to(b, (height, width, 3)).copy()


def _seafloor_albedo(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """(H, W, 3) float64 albedo in [0, 1]: rippled sand, rocks, sea life and pebbles."""
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    sand = np.array([0.62, 0.56, 0.44])
    # Smooth large-scale variation from a few random low-frequency waves, plus ripples.
    tone = np.zeros((height, width))
    for _ in range(6):
        kx, ky = rng.uniform(-0.08, 0.08, 2)
        tone += rng.uniform(0.02, 0.05) * np.cos(kx * xx + ky * yy + rng.uniform(0, 2 * np.pi))
    angle = rng.uniform(0, np.pi)
    ripple = 0.04 * np.sin((np.cos(angle) * xx + np.sin(angle) * yy) * rng.uniform(0.5, 0.8))
    grain = 0.05 * rng.standard_normal((height, width))
    albedo = sand[None, None, :] * (1.0 + tone + ripple + grain)[:, :, None]
    # Rocks: dark grey-brown ellipses with a lighter rim; pebbles: small bright dots.
    n_rocks = max(1, int(height * width / 2500))
    for _ in range(n_rocks):
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        ax, ay = rng.uniform(3, 14, 2)
        rot = rng.uniform(0, np.pi)
        dx, dy = xx - cx, yy - cy
        a = (np.cos(rot) * dx + np.sin(rot) * dy) / ax
        b = (-np.sin(rot) * dx + np.cos(rot) * dy) / ay
        r = np.sqrt(a * a + b * b)
        rock = np.array([0.28, 0.27, 0.25]) * rng.uniform(0.7, 1.3)
        shade = np.clip(1.15 - 0.35 * r, 0.0, 1.2)
        inside = r < 1.0
        albedo[inside] = rock[None, :] * shade[inside][:, None]
    # Sponges and starfish: small saturated red/orange/yellow patches, the colours that water
    # attenuates most, so colour compensation has something to restore.
    n_life = max(1, int(height * width / 3000))
    palette = np.array(
        [(0.80, 0.25, 0.18), (0.90, 0.55, 0.15), (0.85, 0.78, 0.25), (0.70, 0.30, 0.55)]
    )
    for _ in range(n_life):
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        radius = rng.uniform(2.0, 5.0)
        inside = (xx - cx) ** 2 + (yy - cy) ** 2 < radius * radius
        albedo[inside] = palette[rng.integers(len(palette))] * rng.uniform(0.85, 1.1)
    n_pebbles = max(1, int(height * width / 400))
    px = rng.integers(0, width, n_pebbles)
    py = rng.integers(0, height, n_pebbles)
    albedo[py, px] = rng.uniform(0.7, 0.9, (n_pebbles, 1)) * np.array([1.0, 0.97, 0.9])
    return np.clip(albedo, 0.0, 1.0)


@dataclass(frozen=True)
class UnderwaterSequence:
    """A generated underwater sequence.

    Attributes
    ----------
    seafloor : (T, H, W, 3) uint8
        Seafloor frames, RGB.
    water : (Tw, H, W, 3) uint8
        Water-only frames (backscatter + noise), RGB.
    albedo : (H, W + drift_px * (T - 1), 3) uint8
        The seafloor mosaic; frame t sees columns ``offset_t : offset_t + W``. The model
        uses ``albedo / 255`` exactly, so this file is the ground truth.
    backscatter : (H, W, 3) float64
        ``B`` in [0, 1].
    truth : dict
        JSON-ready parameters: A, B, per-frame cone (centre, sigma, peak, floor) and
        albedo offset, noise level.
    """

    seafloor: np.ndarray
    water: np.ndarray
    albedo: np.ndarray
    backscatter: np.ndarray
    truth: dict

    def clean_frame(self, t: int) -> np.ndarray:
        """(H, W, 3) float64 noise-free, unclipped ``A * albedo * cone_t + B`` (0..1) of frame t."""
        f = self.truth["seafloor"][t]
        h, w = self.seafloor.shape[1:3]
        cone = light_cone(h, w, **f["cone"])
        col = f["albedo_offset"][1]
        albedo = self.albedo[:, col : col + w].astype(np.float64) / 255.0
        a = np.asarray(self.truth["A"])
        return a[None, None, :] * albedo * cone[:, :, None] + self.backscatter


def generate_underwater(
    *,
    seed: int = 0,
    frames: int = 40,
    water_frames: int = 8,
    size: tuple[int, int] = (160, 120),
    drift_px: int = 4,
    noise_sigma: float = 1.5,
) -> UnderwaterSequence:
    """Generate the underwater sequence (deterministic in ``seed``).

    Parameters
    ----------
    seed : int
        ``SeedSequence([seed, 9])`` drives everything.
    frames : int
        Seafloor frames (>= 1).
    water_frames : int
        Water-only frames (>= 0).
    size : (W, H)
        Image size, pixels (each >= 8).
    drift_px : int
        Camera motion over the seafloor, columns per frame (>= 0).
    noise_sigma : float
        Gaussian noise standard deviation, 8-bit grey levels.

    Returns
    -------
    UnderwaterSequence
    """
    width, height = (int(s) for s in size)
    if frames < 1 or water_frames < 0:
        raise ParameterError(
            f"need frames >= 1 and water_frames >= 0, got {frames}, {water_frames}"
        )
    if width < 8 or height < 8:
        raise ParameterError(f"underwater image size must be at least 8x8, got {width}x{height}")
    if drift_px < 0 or noise_sigma < 0:
        raise ParameterError("drift_px and noise_sigma must be >= 0")
    rng = np.random.default_rng(np.random.SeedSequence([seed, STREAM_UNDERWATER]))
    mosaic_w = width + drift_px * (frames - 1)
    albedo_u8 = np.rint(_seafloor_albedo(rng, height, mosaic_w) * 255.0).astype(np.uint8)
    albedo = albedo_u8.astype(np.float64) / 255.0
    A = np.array([0.38, 0.78, 0.86]) * rng.uniform(0.95, 1.05, 3)
    B_base = np.array([0.03, 0.13, 0.17]) * rng.uniform(0.9, 1.1, 3)
    B_gradient = 0.4
    B = backscatter(height, width, base=B_base, gradient=B_gradient)
    sigma = 0.35 * min(width, height)
    # The spot drifts from left of centre to right of centre, bobbing vertically.
    phase = rng.uniform(0, 2 * np.pi)
    seafloor = np.empty((frames, height, width, 3), dtype=np.uint8)
    records = []
    for t in range(frames):
        s = t / max(frames - 1, 1)
        centre = (
            float(width * (0.3 + 0.4 * s)),
            float(height * (0.5 + 0.12 * np.sin(2 * np.pi * s + phase))),
        )
        peak = float(0.95 + 0.1 * rng.random())
        cone_params = {"centre": centre, "sigma": float(sigma), "peak": peak, "floor": 0.25}
        cone = light_cone(height, width, **cone_params)
        col = t * drift_px
        clean = A[None, None, :] * albedo[:, col : col + width] * cone[:, :, None] + B
        noisy = clean * 255.0 + rng.normal(0.0, noise_sigma, clean.shape)
        seafloor[t] = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
        records.append(
            {
                "index": t,
                "albedo_offset": [0, col],
                "cone": cone_params,
                "cone_mean": float(cone.mean()),
            }
        )
    water = np.empty((water_frames, height, width, 3), dtype=np.uint8)
    for t in range(water_frames):
        noisy = B * 255.0 + rng.normal(0.0, noise_sigma, B.shape)
        water[t] = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    truth = {
        "model": "I = A * albedo[:, offset:offset+W] * cone_t + B + noise (per channel, 0..1)",
        "seed": int(seed),
        "size": [width, height],
        "frames": frames,
        "water_frames": water_frames,
        "drift_px_per_frame": drift_px,
        "A": [float(v) for v in A],
        "B": {
            "base": [float(v) for v in B_base],
            "vertical_gradient": B_gradient,
            "formula": "B(v) = base * (1 + gradient * (0.5 - v / (H - 1)))",
        },
        "cone_formula": "floor + peak * exp(-((u - cu)^2 + (v - cv)^2) / (2 sigma^2))",
        "noise_sigma_8bit": noise_sigma,
        "albedo_file": "albedo.png",
        "albedo_size": [mosaic_w, height],
        "seafloor": records,
    }
    return UnderwaterSequence(
        seafloor=seafloor, water=water, albedo=albedo_u8, backscatter=B, truth=truth
    )
