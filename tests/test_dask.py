"""Dask executor: same bytes as the local executor, with a local cluster and a scheduler address."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import distributed  # noqa: F401 - a test dependency (make test installs the dask extra)
import pytest
from click.testing import CliRunner

from sparsetools.cli.main import cli

SYNTH = Path(__file__).resolve().parent.parent / "sample_data" / "synthetic"

pytestmark = pytest.mark.slow


def _tree(folder: Path) -> dict[str, str]:
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and ".sparsetools" not in p.parts
    }


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Eight small frames: copies of the three synthetic scans under distinct names."""
    root = tmp_path_factory.mktemp("frames")
    (root / "velodyne").mkdir()
    (root / "calib").mkdir()
    (root / "image_2").mkdir()
    for i in range(8):
        src = f"{i % 3:06d}"
        shutil.copy(SYNTH / "velodyne" / f"{src}.bin", root / "velodyne" / f"{i:06d}.bin")
        shutil.copy(SYNTH / "calib" / f"{src}.txt", root / "calib" / f"{i:06d}.txt")
        shutil.copy(SYNTH / "image_2" / f"{src}.png", root / "image_2" / f"{i:06d}.png")
    return root


def _run(args):
    r = CliRunner().invoke(cli, ["-q", *args])
    assert r.exit_code == 0, r.output
    return r


def test_project_local_vs_dask_local_cluster(frames, tmp_path):
    common = [
        str(frames / "velodyne"),
        "--calib",
        str(frames / "calib"),
        "--image-size",
        "1242x375",
    ]
    _run(["project", *common, "-o", str(tmp_path / "local")])
    _run(["project", *common, "-o", str(tmp_path / "dask"), "--executor", "dask", "--workers", "2"])
    local, dask = _tree(tmp_path / "local"), _tree(tmp_path / "dask")
    assert len([k for k in local if k.endswith(".png")]) == 8
    assert local == dask


def test_lowlight_seeded_output_identical_on_a_scheduler_address(frames, tmp_path):
    from distributed import LocalCluster

    common = [str(frames / "image_2"), "--seed", "3", "--no-flare"]
    _run(["lowlight-synth", *common, "-o", str(tmp_path / "local"), "--workers", "1"])
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        _run(
            [
                "lowlight-synth",
                *common,
                "-o",
                str(tmp_path / "dask"),
                "--executor",
                "dask",
                "--dask-scheduler",
                cluster.scheduler_address,
            ]
        )
    local, dask = _tree(tmp_path / "local"), _tree(tmp_path / "dask")
    pngs = [k for k in local if k.endswith(".png")]
    assert len(pngs) == 8
    assert {k: local[k] for k in pngs} == {k: dask[k] for k in pngs}


def test_unreachable_scheduler_is_a_clear_error(frames, tmp_path, monkeypatch):
    from sparsetools.pipeline import dask as dask_executor

    monkeypatch.setattr(dask_executor, "CONNECT_TIMEOUT", "1s")  # what is refused, not how late
    r = CliRunner().invoke(
        cli,
        [
            "project",
            str(frames / "velodyne"),
            "--calib",
            str(frames / "calib"),
            "--image-size",
            "1242x375",
            "-o",
            str(tmp_path / "o"),
            "--executor",
            "dask",
            "--dask-scheduler",
            "tcp://127.0.0.1:9",
        ],
    )
    assert r.exit_code == 1
    assert "cannot reach the Dask scheduler" in r.stderr and "Traceback" not in r.output


def _busy_frame(item):
    """A frame that holds its thread for a while: its thread and its start and end times."""
    import threading
    import time

    t0 = time.perf_counter()
    time.sleep(0.02)
    return threading.get_ident(), t0, time.perf_counter()


def _most_at_once(spans) -> int:
    events = sorted([(t0, 1) for _, t0, _ in spans] + [(t1, -1) for _, _, t1 in spans])
    most = now = 0
    for _, step in events:
        now += step
        most = max(most, now)
    return most


def test_a_running_cluster_is_used_whole_whatever_workers_says():
    """With a scheduler address, ``workers`` (default 1) is not the cluster's size: the chunks
    in flight follow the threads the scheduler reports, so every worker thread gets frames
    at once (3 chunks in flight, the size of a 1-worker run, would leave one of 4 idle)."""
    from distributed import Client, LocalCluster

    from sparsetools.pipeline.dask import DaskExecutor, cluster_threads

    with LocalCluster(
        n_workers=1, threads_per_worker=4, processes=False, dashboard_address=None
    ) as cluster, Client(cluster) as client:  # fmt: skip
        assert cluster_threads(client) == 4
        ex = DaskExecutor(workers=1, scheduler=cluster.scheduler_address, chunk_size=1)
        spans = list(ex.map(_busy_frame, range(64)))
    assert len(spans) == 64
    assert len({thread for thread, _, _ in spans}) == 4
    assert _most_at_once(spans) == 4
