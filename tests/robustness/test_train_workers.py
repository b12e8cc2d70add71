"""DataLoader workers of train/eval: capped by the batches and the CPUs (one warning line), and
dead within 5 s of a SIGKILL of their parent, also inside a slow item (issue 13, item 1)."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from _processes import alive, children
from sparsetools.train import runtime
from sparsetools.train.runtime import make_loader, usable_loader_workers
from test_train import make_dataset


def test_loader_workers_are_capped_with_one_warning(caplog, monkeypatch):
    monkeypatch.setattr(runtime, "available_cores", lambda: 2)
    monkeypatch.setattr(runtime, "_CAPS_REPORTED", set())
    caplog.set_level(logging.WARNING, logger="sparsetools.train.runtime")
    assert usable_loader_workers(0, 10) == 0
    assert usable_loader_workers(2, 10) == 2 and not caplog.records
    assert usable_loader_workers(100000, 10) == 2
    assert usable_loader_workers(100000, 10) == 2  # every epoch builds a loader: one line
    assert [r.getMessage() for r in caplog.records] == [
        "--loader-workers 100000 capped to 2 (2 CPU(s) available)"
    ]
    assert usable_loader_workers(5, 1) == 1
    assert caplog.records[-1].getMessage() == "--loader-workers 5 capped to 1 (1 batch(es) to load)"
    loader = make_loader(list(range(7)), batch_size=4, order=None, workers=50, seed=0, collate=list)
    assert loader.num_workers == 2  # 2 batches, 2 CPUs
    assert [b for b in loader] == [[0, 1, 2, 3], [4, 5, 6]]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_killing_a_training_run_leaves_no_loader_worker_alive(tmp_path):
    """SIGKILL of a `train --loader-workers 2` run: within 5 s none of its workers is alive."""
    ds = make_dataset(tmp_path / "d")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sparsetools.cli.main",
            "-q",
            "train",
            str(ds),
            "-o",
            str(tmp_path / "run"),
            "--width",
            "4",
            "--batch-size",
            "2",
            "--epochs",
            "1000",
            "--loader-workers",
            "2",
            "--threads",
            "1",
            "--pictures",
            "0",
        ],
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline, kids = time.time() + 90, set()
        while time.time() < deadline and len(kids) < 2 and proc.poll() is None:
            kids = {k for k in children(proc.pid) if alive(k)}
            time.sleep(0.05)
        assert len(kids) >= 2, "the loader never started two workers"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 5.0
        while time.time() < deadline and any(alive(k) for k in kids):
            time.sleep(0.1)
        assert not [k for k in kids if alive(k)], "loader workers outlived their parent"
    finally:
        if proc.poll() is None:
            proc.kill()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_a_worker_busy_with_a_long_item_dies_with_its_parent(tmp_path):
    """torch's own check of the parent runs only between items; a worker inside a slow one
    (a huge image, a stalled network file system) must still die at once."""
    code = textwrap.dedent(
        """
        import time
        from sparsetools.train.runtime import make_loader

        class Slow:
            def __len__(self):
                return 8

            def __getitem__(self, i):
                time.sleep(60)
                return i

        loader = make_loader(Slow(), batch_size=1, order=None, workers=2, seed=0, collate=list)
        for batch in loader:
            pass
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.DEVNULL)
    kids: set[int] = set()
    try:
        deadline = time.time() + 60
        while time.time() < deadline and len(kids) < 2 and proc.poll() is None:
            kids = {k for k in children(proc.pid) if alive(k)}
            time.sleep(0.05)
        assert len(kids) >= 2, "the loader never started two workers"
        time.sleep(1.0)  # both inside their first item
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        deadline = time.time() + 5.0
        while time.time() < deadline and any(alive(k) for k in kids):
            time.sleep(0.1)
        assert not [k for k in kids if alive(k)], "a busy worker outlived its parent"
    finally:
        if proc.poll() is None:
            proc.kill()
        for k in kids:  # only when the test failed: do not leave sleepers behind
            if alive(k):
                os.kill(k, signal.SIGKILL)
