"""Regenerate the pictures of docs/lowlight.md, docs/equalize.md and docs/underwater.md.

Run from the repository root: ``.venv/bin/python docs/img/make_lowlight.py``. Everything is
made by the commands themselves on ``sample_data/`` (the real KITTI frame 000001, CC BY-NC-SA
3.0, see sample_data/kitti/README.md, and the synthetic scene):

- ``lowlight_kitti.png``, ``lowlight_kitti_variants.png``: ``sparsetools project`` (LiDAR
  depth) then ``sparsetools lowlight-synth --variants 3`` on the KITTI frame: day image and
  three night versions; ``lowlight_kitti_crop.png``: a full-resolution crop around a flare.
- ``lowlight_synthetic.png``: the synthetic frame 000000 with its dense depth.
- ``lowlight_bank.png``: the 16 procedural flare patterns of bank seed 0.
- ``lowlight_noise.png``: a crop at exposure ratio 4, 16 and 64 (columns) for the three ELD
  camera profiles (rows), no flares, the same brightness and gamma.
- ``equalize_kitti.png``: two dark night versions (``--brightness 0.4,0.45 --ratio 16,32``)
  before and after ``sparsetools equalize`` (one MCIE table from the first), cropped.
- ``underwater_synthetic.png``: ``sparsetools underwater`` on the synthetic sequence: raw
  frames, corrected, corrected with ``--white-balance``, and the true albedo.
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

from sparsetools.cli.main import cli
from sparsetools.io.image import read_image
from sparsetools.ops.text import put_outlined_text

HERE = Path(__file__).resolve().parent
SAMPLE = HERE.parent.parent / "sample_data"


def sparsetools(*args) -> None:
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    if r.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{r.output}")


def save(name: str, rgb: np.ndarray, *, max_kb: int = 380) -> None:
    """PNG at the highest zlib level, scaled down until it fits the size budget."""
    scale = 1.0
    while True:
        img = (
            rgb
            if scale == 1.0
            else cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        )
        ok, buf = cv2.imencode(".png", img[:, :, ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        assert ok
        if len(buf) <= max_kb * 1024:
            break
        scale *= 0.85
    (HERE / name).write_bytes(buf.tobytes())
    print(f"{name}: {img.shape[1]}x{img.shape[0]}, {len(buf) // 1024} KB")


def shrink(img: np.ndarray, width: int) -> np.ndarray:
    """Scale down to ``width`` pixels (before labelling, so the text stays sharp)."""
    s = width / img.shape[1]
    return cv2.resize(img, (width, int(round(img.shape[0] * s))), interpolation=cv2.INTER_AREA)


def label(img: np.ndarray, text: str) -> np.ndarray:
    size = 0.7 if img.shape[1] > 500 else 0.45
    return put_outlined_text(img.copy(), text, (8, 24), scale=size, thickness=1, outline=2)


def kitti(tmp: Path) -> None:
    src = SAMPLE / "kitti"
    sparsetools("project", "--kitti-object", src, "-o", tmp / "kitti_depth")
    sparsetools("lowlight-synth", src / "image_2", "--depth", tmp / "kitti_depth", "--calib",
                src / "calib", "-o", tmp / "night", "--variants", "3", "--seed", "1")  # fmt: skip
    day = read_image(src / "image_2" / "000001.png")
    manifest = _manifest(tmp / "night")
    nights = []
    for k in range(3):
        r = manifest[k]
        text = (f"night v{k}: s_b {r['brightness']:.2f}, g {r['gamma']:.2f}, "
                f"{r['flare_count']} flare(s), K {r['system_gain']:.2f}, ratio {r['ratio']:.1f}")  # fmt: skip
        nights.append(label(shrink(read_image(tmp / "night" / f"000001_v{k}.png"), 620), text))
    # Noise does not compress: two rows per picture keep them legible under 400 KB.
    save(
        "lowlight_kitti.png", np.vstack([label(shrink(day, 620), "day (KITTI 000001)"), nights[0]])
    )
    save("lowlight_kitti_variants.png", np.vstack(nights[1:]))
    # Full resolution around the brightest flare of v2: glow, streaks and sensor noise.
    r = manifest[2]
    i = int(np.argmax(r["flare_depth"]))
    u, v = r["flare_u"][i], r["flare_v"][i]
    top = int(np.clip(v - 90, 0, day.shape[0] - 180))
    left = int(np.clip(u - 200, 0, day.shape[1] - 400))
    crop = (slice(top, top + 180), slice(left, left + 400))
    night_crop = read_image(tmp / "night" / "000001_v2.png")[crop]
    save("lowlight_kitti_crop.png", np.hstack([day[crop], night_crop]))


def _manifest(folder: Path) -> list[dict]:
    import pyarrow.parquet as pq

    return pq.read_table(folder / "manifest.parquet").to_pylist()


def synthetic(tmp: Path) -> None:
    src = SAMPLE / "synthetic"
    sparsetools("lowlight-synth", src / "image_2" / "000000.png", "--depth",
                src / "depth_gt" / "000000.png", "--calib", src / "calib" / "000000.txt",
                "-o", tmp / "night_synth", "--seed", "3")  # fmt: skip
    rows = [
        label(shrink(read_image(src / "image_2" / "000000.png"), 620), "day (synthetic 000000)")
    ]
    for r in _manifest(tmp / "night_synth")[:1]:
        depths = ", ".join(f"{d:.1f}" for d in r["flare_depth"])
        rows.append(label(shrink(read_image(tmp / "night_synth" / "000000.png"), 620),
                          f"night: sources at depth {depths} m"))  # fmt: skip
    save("lowlight_synthetic.png", np.vstack(rows))


def bank() -> None:
    from sparsetools.ops.flare import flare_bank

    b = flare_bank(seed=0, count=16, size=256)
    tiles = [cv2.resize(p, (160, 160), interpolation=cv2.INTER_AREA) for p in b.patterns]
    grid = np.vstack([np.hstack(tiles[i : i + 8]) for i in range(0, 16, 8)])
    save("lowlight_bank.png", np.rint(grid * 255).astype(np.uint8))


def noise() -> None:
    from sparsetools.ops.lowlight import LowLightParams, lowlight

    day = read_image(SAMPLE / "kitti" / "image_2" / "000001.png")[170:300, 520:760]
    rows = []
    for camera in ("SonyA7S2", "NikonD850", "CanonEOS70D"):
        tiles = []
        for ratio in (4.0, 16.0, 64.0):
            p = LowLightParams(flare=False, camera=camera, ratio=(ratio, ratio),
                               brightness=(0.5, 0.5), gamma=(2.0, 2.0))  # fmt: skip
            night, _ = lowlight(day, rng=7, params=p)
            tiles.append(label(night, f"{camera} x{ratio:g}"))
        rows.append(np.hstack(tiles))
    save("lowlight_noise.png", np.vstack(rows))


def equalize(tmp: Path) -> None:
    src = SAMPLE / "kitti" / "image_2"
    # A darker sequence than the defaults, where equalisation matters most.
    sparsetools("lowlight-synth", src, "-o", tmp / "dark", "--variants", "2", "--seed", "2",
                "--brightness", "0.4,0.45", "--ratio", "16,32", "--no-flare")  # fmt: skip
    sparsetools("equalize", tmp / "dark", "-o", tmp / "eq")
    lut = json.loads((tmp / "eq" / "mcie_lut.json").read_text())
    print(f"MCIE reference: {Path(lut['reference']).name}")
    crop = (slice(60, 340), slice(300, 1000))
    rows = []
    for k in range(2):
        a = label(shrink(read_image(tmp / "dark" / f"000001_v{k}.png")[crop], 420), f"night v{k}")
        b = label(shrink(read_image(tmp / "eq" / f"000001_v{k}.png")[crop], 420),
                  f"MCIE (table of v0), v{k}")  # fmt: skip
        rows.append(np.hstack([a, b]))
    save("equalize_kitti.png", np.vstack(rows))


def underwater(tmp: Path) -> None:
    uw = SAMPLE / "synthetic" / "underwater"
    for name, extra in (("uw", ()), ("uw_wb", ("--white-balance",))):
        sparsetools("underwater", uw / "seafloor", "--water", uw / "water", "-o", tmp / name,
                    "--median-window", "31", *extra)  # fmt: skip
    truth = json.loads((uw / "truth.json").read_text())
    albedo = read_image(uw / "albedo.png")
    w = truth["size"][0]
    cols = []
    for t in (4, 20, 35):
        name = f"{t:06d}.png"
        off = truth["seafloor"][t]["albedo_offset"][1]
        cols.append(np.vstack([
            label(read_image(uw / "seafloor" / name), f"raw {t}"),
            label(read_image(tmp / "uw" / name), "corrected"),
            label(read_image(tmp / "uw_wb" / name), "+ white bal."),
            label(albedo[:, off : off + w], "true albedo"),
        ]))  # fmt: skip
    save("underwater_synthetic.png", np.hstack(cols))


def main() -> None:
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        kitti(tmp)
        synthetic(tmp)
        bank()
        noise()
        equalize(tmp)
        underwater(tmp)


if __name__ == "__main__":
    main()
