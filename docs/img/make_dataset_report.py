"""Regenerate docs/img/dataset_report.png: the demo's dataset report, as headless Chromium
draws it.

Run from the repository root: ``.venv/bin/python docs/img/make_dataset_report.py``. It runs the
demo (``sparsetools demo --out out/demo``; a no-op when it is up to date), which writes
``out/demo/dataset_report.html``, opens that page in Debian's ``chromium`` (headless, at 75 %
zoom so that the whole page fits one picture), cuts the white margin below it and stores it with
a 256-colour palette (under 400 KB).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from click.testing import CliRunner

from sparsetools.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
IMG = Path(__file__).resolve().parent
OUT = Path("out/demo")  # relative: the page shows the paths as the demo gave them
#: CSS pixels of the browser window, and the zoom of the screenshot.
WIDTH, HEIGHT, ZOOM = 1280, 6000, 0.75
MAX_BYTES = 400 * 1024


def main() -> None:
    os.chdir(ROOT)
    res = CliRunner().invoke(cli, ["demo", "--out", str(OUT)])
    if res.exit_code != 0:
        sys.exit(f"sparsetools demo failed:\n{res.output}")
    page = OUT / "dataset_report.html"
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("needs Debian's chromium (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as tmp:
        shot = Path(tmp) / "shot.png"
        cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
               "--no-first-run", f"--user-data-dir={Path(tmp) / 'profile'}",
               f"--force-device-scale-factor={ZOOM}", f"--window-size={WIDTH},{HEIGHT}",
               f"--screenshot={shot}", page.resolve().as_uri()]  # fmt: skip
        subprocess.run(cmd, check=True, capture_output=True, timeout=120,
                       env={**os.environ, "HOME": tmp})  # fmt: skip
        img = cv2.imread(str(shot), cv2.IMREAD_COLOR)
    if img is None:
        sys.exit("chromium wrote no screenshot")
    used = np.flatnonzero((img < 245).any(axis=(1, 2)))
    if used.size == 0 or used[-1] >= img.shape[0] - 1:
        sys.exit(f"the page is blank or taller than {HEIGHT} px: raise HEIGHT")
    img = img[: used[-1] + 16]
    from PIL import Image  # matplotlib's dependency (the viz extra)

    target = IMG / "dataset_report.png"
    for colours in (256, 128, 64):
        pal = Image.fromarray(img[:, :, ::-1]).quantize(colours, dither=Image.Dither.NONE)
        pal.save(target, optimize=True)
        if target.stat().st_size <= MAX_BYTES:
            break
    print(f"{target}: {img.shape[1]}x{img.shape[0]}, {colours} colours, "
          f"{target.stat().st_size / 1024:.0f} KB")  # fmt: skip


if __name__ == "__main__":
    main()
