"""Dask at scale (issue 28): ``project`` in one process against a Dask ``LocalCluster`` of 2
workers (and a local pool of 2 processes), process start to exit.

Run: ``.venv/bin/python benchmarks/bench_dask.py`` (``make bench`` runs it with the others).

1. 4,000 tiny frames (2,000 points, 64x32 maps: ``bench_scale_frames``' frames), where a
   frame's work (~1.5 ms) is of the order of a Dask task's own cost: frames go to the workers
   in chunks sized from the work they report (about 0.25 s per task, ``pipeline/dask.py``).
2. 200 real KITTI frames (``bench_project``'s jittered copies of object frame 000001, 120k
   points to 1242x375).

Goal (issue 28): Dask with 2 workers >= 1.5x one process on the 4,000-frame case. The runs
alternate (serial, local, Dask, serial, ...); medians of ``REPEAT``; every line states the
machine's load. A Dask run pays the cluster's start (two Python processes importing the
package): it is in the figure, as a user pays it. Then a last variant runs on a cluster that
is already running (a ``LocalCluster`` of 2 single-threaded workers in a process of its own,
given by ``--dask-scheduler``, as on a real cluster; warmed by one run first): what a run
costs when the cluster outlives it. That cluster is started after the alternating runs and
stopped after its own, so that its idle processes take nothing from the others.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _timing import interleaved, load, median_seconds
from bench_project import _clouds, cli_env
from bench_scale_frames import SIZE, make_frames

ROOT = Path(__file__).resolve().parent.parent
REPEAT = 3


def _cli() -> list[str]:
    exe = ROOT / ".venv" / "bin" / "sparsetools"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "sparsetools.cli.main"]


def case(name: str, clouds: Path, calib: Path, size: str, n: int, tmp: Path) -> dict:
    runs = iter(range(10**6))
    tag = f"case{len(list(tmp.glob('case*-out0')))}"

    def run(*options: str):
        def go():
            out = tmp / f"{tag}-out{next(runs)}"
            cmd = [*_cli(), "-q", "project", str(clouds), "--calib", str(calib), "--image-size",
                   size, "-o", str(out), "--json", *options]  # fmt: skip
            res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=cli_env())
            assert json.loads(res.stdout)["processed"] == n
            return out

        return go

    variants = {
        "one process": run("--workers", "1"),
        "local 2 workers": run("--workers", "2"),
        "dask 2 workers": run("--executor", "dask", "--workers", "2"),
    }
    before = load()
    t = interleaved(variants, repeat=REPEAT, warmup=0)
    with _running_cluster() as scheduler:
        # warmup: the workers import the package once, as on a cluster that outlives a run
        t["dask, running"] = median_seconds(
            run("--executor", "dask", "--dask-scheduler", scheduler), repeat=REPEAT, warmup=1
        )
    serial = t["one process"]
    print(f"{name}: {n} frames ({before} before, {load()} after)")
    for k, v in t.items():
        print(f"  {k:16s} {v:7.2f} s  {serial / v:5.2f}x one process")
    ratio = serial / t["dask 2 workers"]
    return {"case": name, "seconds": t, "dask_ratio": ratio}


#: A cluster in a process of its own; prints its scheduler's address, lives until killed.
_CLUSTER = """
import logging, time
from distributed import LocalCluster
cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                       dashboard_address=None, silence_logs=logging.ERROR)
print(cluster.scheduler_address, flush=True)
while True:
    time.sleep(60)
"""


@contextlib.contextmanager
def _running_cluster():
    """The address of a cluster running in a process of its own, stopped on exit."""
    cluster = subprocess.Popen([sys.executable, "-c", _CLUSTER], stdout=subprocess.PIPE,
                               text=True, env=cli_env())  # fmt: skip
    try:
        yield cluster.stdout.readline().strip()
    finally:
        cluster.kill()
        cluster.wait()


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bench-dask-") as tmp:
        tmp = Path(tmp)
        velo, _, calib = make_frames(tmp / "tiny", 4000)
        tiny = case("4,000 tiny frames", velo, calib, f"{SIZE[0]}x{SIZE[1]}", 4000, tmp)
        print(f"  goal: dask 2 workers >= 1.5x one process: "
              f"{'met' if tiny['dask_ratio'] >= 1.5 else 'NOT met'} ({tiny['dask_ratio']:.2f}x)")  # fmt: skip
        (tmp / "kitti").mkdir()
        clouds, kcalib, size = _clouds(tmp / "kitti")
        case("200 KITTI frames", clouds, kcalib, size, 200, tmp)


if __name__ == "__main__":
    main()
