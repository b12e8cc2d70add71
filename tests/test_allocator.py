"""The command line's allocator policy (pipeline/allocator.steady_allocator): a frame's
arrays reuse the pages the previous frame freed instead of being faulted in again.

Measured as the minor page faults per "frame" of a loop shaped like ``project``'s (a
120k-point scan, float64 temporaries, a 1242x375 map and its uint16 PNG values), each loop in
a fresh process: with glibc's defaults every frame faults its ~8 MB in again (about 2,000
faults), with the policy a few.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from click.testing import CliRunner

from sparsetools.pipeline import allocator

LOOP = """
import resource, sys
import numpy as np
if sys.argv[1] == "steady":
    from sparsetools.pipeline.allocator import steady_allocator
    assert steady_allocator()
def frame(i):
    pts = np.full((120_000, 4), i, np.float32)
    x = pts[:, 0].astype(np.float64) * 2.0
    y = x + 1.0
    depth = np.zeros((375, 1242), np.float32)
    depth[0, 0] = y[0]
    return float((depth * 256).astype(np.uint16).sum())
frame(0)
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for i in range(30):
    frame(i)
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 30)
"""


def _faults_per_frame(mode: str) -> float:
    out = subprocess.run(
        [sys.executable, "-c", LOOP, mode], capture_output=True, text=True, check=True
    )
    return float(out.stdout)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_frames_reuse_the_pages_the_last_frame_freed():
    default, steady = _faults_per_frame("default"), _faults_per_frame("steady")
    pages = (120_000 * 4 * 4 + 2 * 120_000 * 8 + 375 * 1242 * (4 + 4 + 2)) / 4096
    assert steady < 0.05 * pages, (steady, pages)  # a few faults, not the frame's pages
    assert default > 10 * max(steady, 1.0), (default, steady)  # what it saves, measured


def test_a_batch_command_sets_it_for_its_process_and_help_does_not(monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(allocator, "steady_allocator", lambda: calls.append(1) or True)
    from sparsetools.cli.main import cli

    r = CliRunner().invoke(cli, ["beams", "--help"])
    assert r.exit_code == 0 and calls == []  # --help stays light: no pipeline import
    (tmp_path / "empty").mkdir()
    CliRunner().invoke(
        cli, ["beams", str(tmp_path / "empty"), "--n", "4", "-o", str(tmp_path / "o")]
    )
    assert calls == [1]
