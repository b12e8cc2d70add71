"""Low-light synthesis per 1242x375 image, and the one-off flare-bank build, reported apart.

Ours: ``lowlight`` with the cached procedural flare bank, the 256-entry linearisation table
and ELD noise. Reference: the same sampled record composed the straightforward way: every
flare pattern synthesised afresh for the image (no bank), ``numpy.power`` over the whole
image for the linearisation, the same noise. Both produce the same kind of image; the
reference shows what the bank and the table save. Then where our time goes.

Input: the real KITTI frame in ../shared/data/real when present, else sample_data/synthetic,
else a random image with a random depth map.

Run: ``.venv/bin/python benchmarks/bench_lowlight.py``
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import compare, median_seconds

ROOT = Path(__file__).resolve().parent.parent
REAL = ROOT.parent / "shared" / "data" / "real" / "kitti-depth-gt-metric3d"
K = np.array([[721.5377, 0.0, 609.5593], [0.0, 721.5377, 172.854], [0.0, 0.0, 1.0]])


def load_input():
    from sparsetools.io.image import read_depth_png, read_image

    if (REAL / "rgb" / "0000000050.png").is_file():
        return (read_image(REAL / "rgb" / "0000000050.png"),
                read_depth_png(REAL / "depth" / "0000000050.png"), "real KITTI 0000000050")  # fmt: skip
    synth = ROOT / "sample_data" / "synthetic"
    if (synth / "image_2" / "000000.png").is_file():
        return (read_image(synth / "image_2" / "000000.png"),
                read_depth_png(synth / "depth_gt" / "000000.png"), "sample_data/synthetic")  # fmt: skip
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (375, 1242, 3), dtype=np.uint8)
    depth = rng.uniform(2, 80, (375, 1242)).astype(np.float32)
    return image, depth, "random"


def reference_lowlight(image, record):
    """Straightforward composition of a sampled record (patterns built per image)."""
    import cv2

    from sparsetools.ops.flare import _make_ghost, _make_pattern
    from sparsetools.ops.noise import add_sensor_noise

    g = record.gamma
    linear = np.power(record.brightness * image.astype(np.float64) / 255.0, g)
    h, w = image.shape[:2]
    for f in record.flares:
        pattern, _ = _make_pattern(record.bank_seed, f.pattern, record.bank_size)
        sprite = cv2.resize(pattern, (f.side, f.side), interpolation=cv2.INTER_AREA)
        c = (f.side - 1) / 2
        M = cv2.getRotationMatrix2D((c, c), f.rotation, 1.0)
        sprite = cv2.warpAffine(sprite, M, (f.side, f.side))
        lin = np.power(np.maximum(sprite.astype(np.float64), 0), g) * f.color * f.intensity
        top, left = f.v - f.side // 2, f.u - f.side // 2
        r0, c0 = max(top, 0), max(left, 0)
        r1, c1 = min(top + f.side, h), min(left + f.side, w)
        if r0 < r1 and c0 < c1:
            linear[r0:r1, c0:c1] += lin[r0 - top : r1 - top, c0 - left : c1 - left]
        for gh in f.ghosts:
            _make_ghost(record.bank_seed, gh.shape)  # built per ghost, as without a bank
    n = record.noise
    scale = n.saturation / n.ratio
    noisy = add_sensor_noise(linear * scale, n) / scale
    return np.rint(np.power(np.clip(noisy, 0, 1), 1 / g) * 255).astype(np.uint8)


def main() -> None:
    from sparsetools.ops.flare import build_flare_bank, flare_bank
    from sparsetools.ops.lowlight import LowLightParams, lowlight

    image, depth, source = load_input()
    print(f"input: {source}, {image.shape[1]}x{image.shape[0]}")
    t_bank = median_seconds(lambda: build_flare_bank(seed=0, count=16, size=256), repeat=3)
    print(f"{'flare bank build (16 patterns of 256 px, once)':<48} {t_bank * 1e3:9.1f} ms")
    bank = flare_bank()
    seeds = iter(range(10**6))
    # Fixed flare count so ours and the reference do the same work per image.
    params = LowLightParams(flare_count=(6, 6))
    _, record = lowlight(image, depth=depth, K=K, rng=0, params=params, bank=bank)
    print(f"flares per image: {record.flare_count}, camera {record.noise.camera}")
    compare(
        "lowlight per 1242x375 image (6 flares, ELD)",
        lambda: lowlight(image, depth=depth, K=K, rng=next(seeds), params=params, bank=bank),
        lambda: reference_lowlight(image, record),
        reference_name="per-image patterns",
        repeat=7,
    )
    # Where the time goes (ours).
    for name, p in (
        ("  no flare, no noise", LowLightParams(flare=False, noise="none")),
        ("  flares only", LowLightParams(flare_count=(6, 6), noise="none")),
        ("  ELD noise only", LowLightParams(flare=False)),
        ("  Gaussian noise only", LowLightParams(flare=False, noise="gaussian")),
    ):
        t = median_seconds(lambda p=p: lowlight(image, depth=depth, rng=next(seeds), params=p,
                                                bank=bank), repeat=7)  # fmt: skip
        print(f"{name:<48} {t * 1e3:9.1f} ms")
    # Replay from a record costs the same as sampling.
    t0 = time.perf_counter()
    for _ in range(5):
        lowlight(image, record=record, bank=bank)
    print(f"{'  replay from a record':<48} {(time.perf_counter() - t0) / 5 * 1e3:9.1f} ms")


if __name__ == "__main__":
    main()
