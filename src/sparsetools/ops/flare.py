"""Procedural lens-flare patterns (no downloads) and their placement in an image.

Flare7K's captured patterns cannot be fetched here, so a seeded bank is synthesised once:

- **Wave optics** (after Wu et al., ICCV 2021): a dirty aperture (circular or polygonal iris
  with opaque dust dots and scratches) is the pupil; its point-spread function at wavelength
  ``lambda`` is ``|FFT(pupil)|^2`` magnified by ``lambda / 550 nm`` (the focal-plane coordinate
  is proportional to the wavelength). 31 wavelengths over 380-740 nm are summed with Gaussian
  R, G, B spectral responses, which gives the coloured fringes of real streaks.
- **Glow**: a Gaussian core plus a ``1 / (1 + (r / r0)^2)`` halo.
- **Ghosts**: soft discs or polygons (aperture images) placed at render time along the line
  from the light source through the image centre.

Patterns are stored like Flare7K's, as display-referred values in [0, 1] (the linear PSF is
amplified so the core saturates, clipped and encoded with exponent 1/2.2); the composer
linearises them with the image's random gamma. The bank is deterministic from its seed and
cached in memory (an on-disk copy is :mod:`sparsetools.io.flare_bank`).
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..errors import ParameterError
from ..validate import check_int_range, check_odd, check_pair, check_positive, check_shape

__all__ = [
    "BANK_VERSION",
    "FlareBank",
    "FlareRecord",
    "GhostRecord",
    "build_flare_bank",
    "flare_bank",
    "render_flares",
    "sample_flares",
]

log = logging.getLogger(__name__)

#: Bump when the generator changes, so stale on-disk banks are rebuilt.
BANK_VERSION = 1

_WAVELENGTHS_NM = np.linspace(380.0, 740.0, 31)
_REF_WAVELENGTH_NM = 550.0
# Gaussian spectral responses (centre, sigma) in nm of a typical colour filter array.
_RGB_RESPONSE = ((600.0, 40.0), (540.0, 40.0), (455.0, 30.0))
_DISPLAY_GAMMA = 2.2
_GHOST_SIZE = 64


@dataclass(frozen=True)
class FlareBank:
    """A seeded set of flare patterns.

    Attributes
    ----------
    seed, size : int
    patterns : (N, size, size, 3) float32, display-referred values in [0, 1]
        Starburst + glow, centred on pixel coordinate ((size - 1) / 2, (size - 1) / 2).
    ghosts : (G, 64, 64) float32 in [0, 1]
        Ghost shapes (soft disc or polygon).
    descriptions : tuple of str
        What each pattern is made of (for manifests and debugging).
    """

    seed: int
    size: int
    patterns: np.ndarray
    ghosts: np.ndarray
    descriptions: tuple[str, ...] = field(default=())

    @property
    def count(self) -> int:
        return int(self.patterns.shape[0])


def _centred_grid(n: int, centre: float) -> tuple[np.ndarray, np.ndarray]:
    c = np.arange(n, dtype=np.float32) - np.float32(centre)
    return c[None, :], c[:, None]


def _pupil(gen: np.random.Generator, n: int) -> tuple[np.ndarray, str]:
    """Amplitude transmission of a dirty aperture on an (n, n) grid, centred at n/2."""
    import cv2

    x, y = _centred_grid(n, n / 2)
    radius = n * gen.uniform(0.09, 0.15)
    blades = int(gen.choice([0, 5, 6, 7, 8]))
    if blades:
        # Regular polygon: inside when the projection on every edge normal is below the apothem.
        phase = gen.uniform(0, 2 * math.pi)
        apothem = radius * math.cos(math.pi / blades)
        inside = np.ones((n, n), bool)
        for k in range(blades):
            a = phase + 2 * math.pi * (k + 0.5) / blades
            inside &= x * math.cos(a) + y * math.sin(a) <= apothem
        pupil = inside.astype(np.float32)
    else:
        pupil = (x * x + y * y <= radius * radius).astype(np.float32)
    n_dust = int(gen.integers(10, 60))
    for _ in range(n_dust):
        r = radius * math.sqrt(gen.uniform(0, 1))
        a = gen.uniform(0, 2 * math.pi)
        centre = (int(round(n / 2 + r * math.cos(a))), int(round(n / 2 + r * math.sin(a))))
        dot = max(1, int(round(radius * gen.uniform(0.01, 0.06))))
        cv2.circle(pupil, centre, dot, float(gen.uniform(0.0, 0.3)), -1, lineType=cv2.LINE_AA)
    n_scratch = int(gen.integers(0, 5))
    for _ in range(n_scratch):
        a = gen.uniform(0, math.pi)
        off = gen.uniform(-0.8, 0.8) * radius
        half = radius * gen.uniform(0.5, 1.2)
        cx = n / 2 - off * math.sin(a)
        cy = n / 2 + off * math.cos(a)
        p0 = (int(round(cx - half * math.cos(a))), int(round(cy - half * math.sin(a))))
        p1 = (int(round(cx + half * math.cos(a))), int(round(cy + half * math.sin(a))))
        cv2.line(pupil, p0, p1, 0.0, int(gen.integers(1, 3)), lineType=cv2.LINE_AA)
    shape = f"iris{blades}" if blades else "circle"
    return pupil, f"{shape}+dust{n_dust}+scratch{n_scratch}"


def _spectral_weights() -> np.ndarray:
    """(31, 3) weights of each wavelength in R, G, B; each channel sums to 1 (white = grey)."""
    w = np.stack(
        [np.exp(-0.5 * ((_WAVELENGTHS_NM - mu) / sd) ** 2) for mu, sd in _RGB_RESPONSE], axis=1
    )
    return (w / w.sum(axis=0, keepdims=True)).astype(np.float32)


def _wave_optics_psf(pupil: np.ndarray, size: int) -> np.ndarray:
    """RGB PSF (size, size, 3) float32 of ``pupil``, peak 1, centred at (size - 1) / 2."""
    import cv2

    n = pupil.shape[0]
    field_ = np.fft.fft2(np.fft.ifftshift(pupil))
    psf_ref = np.fft.fftshift(field_.real**2 + field_.imag**2).astype(np.float32)
    psf_ref /= psf_ref.max()
    weights = _spectral_weights()
    planes = [np.zeros((n, n), np.float32) for _ in range(3)]
    c_src, c_dst = n / 2, (n - 1) / 2  # half-pixel shift so the centre lands between pixels
    for lam, w in zip(_WAVELENGTHS_NM, weights, strict=True):
        s = lam / _REF_WAVELENGTH_NM
        M = np.array([[s, 0, c_dst - s * c_src], [0, s, c_dst - s * c_src]], np.float64)
        psf = cv2.warpAffine(psf_ref, M, (n, n), flags=cv2.INTER_LINEAR, borderValue=0.0)
        psf *= np.float32(1.0 / (s * s))  # a magnified PSF keeps its energy
        for plane, wc in zip(planes, w, strict=True):
            plane += psf * wc
    rgb = cv2.resize(np.dstack(planes), (size, size), interpolation=cv2.INTER_AREA)
    return rgb / rgb.max()


def _radial(size: int) -> np.ndarray:
    x, y = _centred_grid(size, (size - 1) / 2)
    return np.sqrt(x * x + y * y)


def _edge_window(size: int) -> np.ndarray:
    """1 inside 0.25 size, cosine taper to 0 at 0.5 size: no visible edge."""
    r = _radial(size) / size
    t = np.clip((r - 0.25) / 0.25, 0, 1)
    return (0.5 + 0.5 * np.cos(np.pi * t)).astype(np.float32)


def _make_pattern(seed: int, index: int, size: int) -> tuple[np.ndarray, str]:
    gen = np.random.default_rng([seed, index, BANK_VERSION])
    pupil, desc = _pupil(gen, 2 * size)
    streaks = _wave_optics_psf(pupil, size) * np.float32(
        math.exp(gen.uniform(math.log(30), math.log(400)))
    )
    r = _radial(size)
    sigma = size * gen.uniform(0.01, 0.03)
    r0 = size * gen.uniform(0.02, 0.07)
    halo = gen.uniform(0.15, 0.5)
    glow = np.exp(-0.5 * (r / sigma) ** 2) + halo / (1 + (r / r0) ** 2)
    tint = 1.0 + gen.uniform(-0.15, 0.15, size=3)  # glass dispersion tints the halo slightly
    linear = streaks + glow[:, :, None].astype(np.float32) * tint.astype(np.float32)
    linear *= _edge_window(size)[:, :, None]
    display = np.clip(linear, 0, 1) ** np.float32(1 / _DISPLAY_GAMMA)
    return display.astype(np.float32), f"{desc}+glow"


def _make_ghost(seed: int, index: int) -> np.ndarray:
    import cv2

    gen = np.random.default_rng([seed, 10_000 + index, BANK_VERSION])
    n = _GHOST_SIZE
    x, y = _centred_grid(n, (n - 1) / 2)
    radius = n * gen.uniform(0.3, 0.4)
    sides = int(gen.choice([0, 5, 6, 8]))
    if sides:
        phase = gen.uniform(0, 2 * math.pi)
        apothem = radius * math.cos(math.pi / sides)
        d = np.full((n, n), -np.inf, np.float32)
        for k in range(sides):
            a = phase + 2 * math.pi * (k + 0.5) / sides
            d = np.maximum(d, x * math.cos(a) + y * math.sin(a) - apothem)
    else:
        d = np.sqrt(x * x + y * y) - radius
    inside = (d <= 0).astype(np.float32)
    rim = np.exp(-0.5 * (d / 1.5) ** 2) * gen.uniform(0.0, 0.8)
    ghost = cv2.GaussianBlur(inside * gen.uniform(0.3, 1.0) + rim, (0, 0), gen.uniform(0.8, 3.0))
    return (ghost / max(float(ghost.max()), 1e-6)).astype(np.float32)


def build_flare_bank(
    *, seed: int = 0, count: int = 16, size: int = 256, ghosts: int = 8
) -> FlareBank:
    """Synthesise a flare bank (uncached; see :func:`flare_bank`).

    Parameters
    ----------
    seed : int
        Pattern ``i`` depends only on (seed, i), so banks of different ``count`` share patterns.
    count : int
        Number of starburst + glow patterns.
    size : int
        Side of each pattern in pixels (even, 32..1024).
    ghosts : int
        Number of ghost shapes.
    """
    count = check_int_range(count, "count", low=1, high=256)
    size = check_int_range(size, "size", low=32, high=1024)
    if size % 2:
        raise ParameterError(f"must be even (a pattern centred between pixels), got {size}",
                             param="size")  # fmt: skip
    ghosts = check_int_range(ghosts, "ghosts", low=1, high=64)
    made = [_make_pattern(seed, i, size) for i in range(count)]
    patterns = np.stack([m[0] for m in made])
    ghost_arr = np.stack([_make_ghost(seed, i) for i in range(ghosts)])
    return FlareBank(seed, size, patterns, ghost_arr, tuple(m[1] for m in made))


@functools.lru_cache(maxsize=8)
def _cached_bank(seed: int, count: int, size: int) -> FlareBank:
    bank = build_flare_bank(seed=seed, count=count, size=size)
    bank.patterns.setflags(write=False)  # shared by every caller of the cache
    bank.ghosts.setflags(write=False)
    return bank


def flare_bank(*, seed: int = 0, count: int = 16, size: int = 256) -> FlareBank:
    """The flare bank for (seed, count, size), built once per process and reused.

    Parameters
    ----------
    seed, count, size : int
        See :func:`build_flare_bank`.

    Returns
    -------
    FlareBank
        Read-only arrays. An on-disk copy (to build it once for a whole process pool) is
        :func:`sparsetools.io.flare_bank.cached_flare_bank`.
    """
    seed = check_int_range(seed, "seed")
    count = check_int_range(count, "count", low=1, high=256)
    size = check_int_range(size, "size", low=32, high=1024)
    return _cached_bank(seed, count, size)


# --------------------------------------------------------------------------- placement


@dataclass
class GhostRecord:
    """One ghost: centre (u, v) in pixels, radius in pixels, relative intensity, shape id."""

    u: float
    v: float
    radius: float
    intensity: float
    shape: int


@dataclass
class FlareRecord:
    """One flare as placed in an image.

    Attributes
    ----------
    u, v : int
        Light-source pixel (column, row), 0-based.
    depth : float or None
        Depth of that pixel in metres (when placed from a depth map).
    point : [x, y, z] or None
        ``P = depth * K^-1 [u v 1]^T`` in camera coordinates, metres (when K is known).
    side : int
        Side of the rendered pattern in pixels (odd): ``scale * min(H, W)``.
    pattern : int
        Index into the flare bank.
    rotation : float
        Degrees, counter-clockwise.
    intensity : float
        Multiplier of the pattern in linear light.
    color : [r, g, b]
        Light-source colour (max component 1).
    ghosts : list of GhostRecord
    """

    u: int
    v: int
    depth: float | None
    point: list[float] | None
    side: int
    pattern: int
    rotation: float
    intensity: float
    color: list[float]
    ghosts: list[GhostRecord] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> FlareRecord:
        return cls(
            u=int(d["u"]), v=int(d["v"]),
            depth=None if d.get("depth") is None else float(d["depth"]),
            point=None if d.get("point") is None else [float(p) for p in d["point"]],
            side=int(d["side"]), pattern=int(d["pattern"]), rotation=float(d["rotation"]),
            intensity=float(d["intensity"]), color=[float(c) for c in d["color"]],
            ghosts=[
                GhostRecord(float(g["u"]), float(g["v"]), float(g["radius"]),
                            float(g["intensity"]), int(g["shape"]))
                for g in d.get("ghosts", [])
            ],
        )  # fmt: skip


def _light_colour(gen: np.random.Generator) -> list[float]:
    """Street-light colours: sodium orange to cool LED white, sometimes a red tail light."""
    if gen.uniform() < 0.1:
        rgb = np.array([1.0, gen.uniform(0.1, 0.3), gen.uniform(0.05, 0.2)])
    else:
        t = gen.uniform()
        warm = np.array([1.0, 0.72, 0.38])
        cool = np.array([0.86, 0.93, 1.0])
        rgb = (1 - t) * warm + t * cool
    return [float(c) for c in rgb / rgb.max()]


def sample_flares(
    rng: np.random.Generator,
    height: int,
    width: int,
    *,
    bank: FlareBank,
    scale_range: tuple[float, float],
    amount_range: tuple[float, float],
    count_range: tuple[int, int],
    depth: np.ndarray | None = None,
    intrinsics: np.ndarray | None = None,
    max_depth: float = 20.0,
    ghosts: bool = True,
) -> dict:
    """Draw the flares of one image (DepthDark LLDG flare simulation).

    ``s_F ~ logU(scale_range)``, ``F ~ logU(amount_range)``,
    ``N_F = clip(max(floor(F / s_F + 0.5), 1), *count_range)``. Light sources sit at pixels
    whose depth ``z`` satisfies ``0 < z <= max_depth`` (with ``intrinsics``, their 3-D point
    ``P = z K^-1 [u v 1]^T`` is recorded); without a depth map they are uniform over the image.

    Parameters
    ----------
    rng : numpy.random.Generator
    height, width : int
        Image size in pixels.
    bank : FlareBank
    scale_range : (float, float)
        Pattern side as a fraction of ``min(height, width)``.
    amount_range : (float, float)
        Total flare amount ``F``.
    count_range : (int, int)
        Clip range of ``N_F``.
    depth : (H, W) float, metres, optional
    intrinsics : (3, 3) float, optional
    max_depth : float, metres
    ghosts : bool
        Add 0-3 ghosts per flare.

    Returns
    -------
    dict
        ``source`` ("depth", "uniform" or "depth-none-in-range": no eligible pixel, so no flare),
        ``scale``, ``amount``, ``count`` and ``flares`` (list of :class:`FlareRecord`).
    """
    check_int_range(height, "height", low=1)
    check_int_range(width, "width", low=1)
    check_pair(scale_range, "scale_range", low=0.0, strict=True)
    check_pair(amount_range, "amount_range", low=0.0, strict=True)
    check_pair(count_range, "count_range", low=0, integer=True)
    check_positive(max_depth, "max_depth")
    if depth is not None:
        check_shape(np.asarray(depth), f"({height}, {width})", "depth")
    if intrinsics is not None:
        check_shape(np.asarray(intrinsics), "(3, 3)", "intrinsics")
    s_f = math.exp(rng.uniform(math.log(scale_range[0]), math.log(scale_range[1])))
    amount = math.exp(rng.uniform(math.log(amount_range[0]), math.log(amount_range[1])))
    n_f = max(math.floor(amount / s_f + 0.5), 1)
    n_f = int(min(max(n_f, count_range[0]), count_range[1]))
    short = min(height, width)
    side = max(9, int(round(s_f * short)))
    side += 1 - side % 2  # odd, so the source sits on the centre pixel
    if depth is not None:
        d = np.asarray(depth)
        eligible = np.flatnonzero(np.isfinite(d) & (d > 0) & (d <= max_depth))
        source = "depth" if eligible.size else "depth-none-in-range"
        if not eligible.size:
            n_f = 0
    else:
        source = "uniform"
    K_inv = None if intrinsics is None else np.linalg.inv(np.asarray(intrinsics, np.float64))
    flares: list[FlareRecord] = []
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    for _ in range(n_f):
        z = None
        point = None
        if depth is not None:
            idx = int(eligible[rng.integers(eligible.size)])
            v, u = divmod(idx, width)
            z = float(d.flat[idx])
            if K_inv is not None:
                point = [float(p) for p in z * (K_inv @ np.array([u, v, 1.0]))]
        else:
            u = int(rng.integers(width))
            v = int(rng.integers(height))
        rec = FlareRecord(
            u=int(u),
            v=int(v),
            depth=z,
            point=point,
            side=side,
            pattern=int(rng.integers(bank.count)),
            rotation=float(rng.uniform(0, 360)),
            intensity=float(rng.uniform(0.5, 1.0)),
            color=_light_colour(rng),
        )
        if ghosts:
            for _g in range(int(rng.integers(0, 4))):
                t = rng.uniform(-1.3, -0.2)  # mirrored through the centre, as most ghosts are
                gu, gv = centre + t * (np.array([u, v], float) - centre)
                rec.ghosts.append(GhostRecord(
                    u=float(gu), v=float(gv), radius=float(short * rng.uniform(0.01, 0.06)),
                    intensity=float(rng.uniform(0.02, 0.12)),
                    shape=int(rng.integers(bank.ghosts.shape[0])),
                ))  # fmt: skip
        flares.append(rec)
    return {"source": source, "scale": float(s_f), "amount": float(amount), "count": n_f,
            "flares": flares}  # fmt: skip


def _paste_add(canvas: np.ndarray, sprite: np.ndarray, cu: int, cv: int) -> None:
    """Add ``sprite`` (odd sides) to ``canvas`` centred on pixel (cu, cv), clipped to the image."""
    h, w = sprite.shape[:2]
    top, left = cv - h // 2, cu - w // 2
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + h, canvas.shape[0]), min(left + w, canvas.shape[1])
    if r0 >= r1 or c0 >= c1:
        return
    canvas[r0:r1, c0:c1] += sprite[r0 - top : r1 - top, c0 - left : c1 - left]


def _resized(img: np.ndarray, side: int) -> np.ndarray:
    import cv2

    interp = cv2.INTER_AREA if side < img.shape[0] else cv2.INTER_LINEAR
    return cv2.resize(img, (side, side), interpolation=interp)


def render_flares(
    height: int, width: int, flares: list[FlareRecord], *, bank: FlareBank, gamma: float
) -> np.ndarray:
    """Sum of the flares in linear light: ``sum_i [ss(L; s_F, P_i)]^gamma`` (plus ghosts).

    Parameters
    ----------
    height, width : int
    flares : list of FlareRecord
    bank : FlareBank
    gamma : float
        Linearisation exponent of the image (display-referred patterns are raised to it).

    Returns
    -------
    (H, W, 3) float64
        Linear-light flare image (values may exceed 1 near the sources).
    """
    import cv2

    check_int_range(height, "height", low=1)
    check_int_range(width, "width", low=1)
    check_positive(gamma, "gamma")
    canvas = np.zeros((height, width, 3), np.float64)
    for f in flares:
        if not 0 <= f.pattern < bank.count:
            raise ParameterError(
                f"flare pattern {f.pattern} is not in the bank (0..{bank.count - 1})"
            )
        check_odd(f.side, "side", low=1)  # pixels, centred on the light source
        sprite = _resized(bank.patterns[f.pattern], f.side)
        c = (f.side - 1) / 2
        M = cv2.getRotationMatrix2D((c, c), f.rotation, 1.0)
        sprite = cv2.warpAffine(sprite, M, (f.side, f.side), flags=cv2.INTER_LINEAR, borderValue=0)
        lin = np.maximum(sprite.astype(np.float64), 0.0) ** gamma
        lin *= np.asarray(f.color, np.float64) * f.intensity
        _paste_add(canvas, lin, f.u, f.v)
        for g in f.ghosts:
            if not 0 <= g.shape < bank.ghosts.shape[0]:
                raise ParameterError(f"ghost shape {g.shape} is not in the bank")
            side = max(3, 2 * int(round(g.radius)) + 1)
            shape = np.maximum(_resized(bank.ghosts[g.shape], side).astype(np.float64), 0.0)
            glin = (shape**gamma)[:, :, None] * (np.asarray(f.color) * g.intensity)
            _paste_add(canvas, glin, int(round(g.u)), int(round(g.v)))
    return canvas
