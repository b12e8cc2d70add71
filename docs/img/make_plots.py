"""Example pictures of the --plot options (docs/beams.md, docs/accumulate.md, docs/train.md).

Run from the repository root: ``.venv/bin/python docs/img/make_plots.py`` (about 20 s; the
sample data only, matplotlib needed: ``pip install 'sparsetools[viz]'``). Writes
docs/img/beams_ring_report.png (``beams --report --plot`` of the KITTI sample scan),
docs/img/accumulate_removals.png (``accumulate --plot`` of a synthetic 12-frame video) and
docs/img/eval_plot.png (``eval --plot`` of the synthetic sample's projected scans against its
ground truth, holes filled with the nearest value).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

from click.testing import CliRunner

from sparsetools.cli.main import cli

ROOT = Path(__file__).resolve().parent.parent.parent
IMG = ROOT / "docs" / "img"
SAMPLE = ROOT / "sample_data"


def sh(*args) -> str:
    res = CliRunner().invoke(cli, ["-q", *map(str, args)])
    if res.exit_code != 0:
        sys.exit(f"sparsetools {' '.join(map(str, args))} failed:\n{res.output}{res.stderr}")
    return res.stdout


def keep(src: Path, name: str) -> None:
    shutil.copyfile(src, IMG / name)
    print(f"docs/img/{name}")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        sh("beams", "--report", "--plot", SAMPLE / "kitti" / "velodyne" / "000001.bin",
           "-o", t / "rings")  # fmt: skip
        keep(t / "rings" / "ring_report.png", "beams_ring_report.png")

        sh("synth-scene", "-o", t / "video", "--video", "--sequences", 1, "--frames", 12,
           "--image-size", "416x128", "--seed", 3)  # fmt: skip
        print(sh("accumulate", t / "video", "-o", t / "acc", "--neighbours", 2, "--plot"))
        keep(t / "acc" / "removals.png", "accumulate_removals.png")

        syn = SAMPLE / "synthetic"
        sh("project", syn / "velodyne", "--calib", syn / "calib", "--image", syn / "image_2",
           "-o", t / "proj")  # fmt: skip
        sh("eval", "--pred", t / "proj", "--gt", syn / "depth_gt", "--fill", "nearest",
           "-o", t / "eval" / "metrics.json", "--plot")  # fmt: skip
        keep(t / "eval" / "metrics.png", "eval_plot.png")


if __name__ == "__main__":
    main()
