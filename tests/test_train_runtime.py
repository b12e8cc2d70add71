"""Training runtime: the thread default, torch settings and checkpoints written on a
background thread (issue 18). The DataLoader workers' bounds are tested in
tests/robustness/test_train_workers.py (issue 13)."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import textwrap

import pytest

torch = pytest.importorskip("torch")

from sparsetools.errors import OutputError  # noqa: E402
from sparsetools.train import runtime  # noqa: E402
from sparsetools.train.runtime import (  # noqa: E402
    BackgroundWriter,
    background_saves,
    copy_file,
    default_threads,
    resolve_threads,
    save_torch,
    torch_settings,
)


# -- the thread default ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("free", "cores", "cap", "expected"),
    [
        (2.0, 2, 8, 2),  # idle: every core
        (1.6, 2, 8, 2),  # rounds to the nearest
        (1.4, 2, 8, 1),
        (0.0, 2, 8, 1),  # overloaded: one thread, never 0
        (12.2, 16, 64, 12),
        (16.0, 16, 4, 4),  # OMP_NUM_THREADS / physical cores bound it
        (3.0, 2, 8, 2),  # never more than the CPUs it may use
        (-1.0, 3, 8, 1),  # nonsense is clamped
    ],
)
def test_default_threads_counts_the_free_cores(free, cores, cap, expected):
    got = default_threads(free=free, cores=cores, cap=cap)
    assert got == expected
    assert 1 <= got <= min(cores, cap)


def test_free_cores_measures_now_not_the_last_minute(monkeypatch):
    """/proc/stat deltas: a CPU idle 25 % of the interval counts 0.25; without /proc/stat the
    1-minute load average is the fallback."""
    samples = iter([{0: (100, 1000), 1: (500, 1000)}, {0: (125, 1100), 1: (600, 1100)}])
    monkeypatch.setattr(runtime, "_cpu_times", lambda cpus: next(samples))
    monkeypatch.setattr(runtime.os, "sched_getaffinity", lambda pid: {0, 1})
    assert math.isclose(runtime.free_cores(interval=0.0), 0.25 + 1.0)
    monkeypatch.setattr(runtime, "_cpu_times", lambda cpus: None)
    monkeypatch.setattr(runtime.os, "getloadavg", lambda: (1.5, 0.0, 0.0))
    monkeypatch.setattr(runtime.os, "cpu_count", lambda: 4)
    assert math.isclose(runtime.free_cores(interval=0.0), 2 - 1.5 * 2 / 4)


def test_default_threads_reads_this_machine():
    measured = runtime.free_cores(interval=0.05)
    assert 0.0 <= measured <= runtime.available_cores()
    n = default_threads()
    assert 1 <= n <= runtime.available_cores()
    assert resolve_threads(3) == 3 and resolve_threads(None) >= 1


def test_torch_settings_sets_and_restores_everything():
    from torch.utils import deterministic

    before = (
        torch.are_deterministic_algorithms_enabled(),
        deterministic.fill_uninitialized_memory,
        torch.get_num_threads(),
    )
    with torch_settings(1, torch.device("cpu")):
        assert torch.are_deterministic_algorithms_enabled()
        assert not torch.is_deterministic_algorithms_warn_only_enabled()
        assert not deterministic.fill_uninitialized_memory
        assert torch.get_num_threads() == 1
    with torch_settings(None, torch.device("cpu")):
        assert torch.get_num_threads() >= 1
    after = (
        torch.are_deterministic_algorithms_enabled(),
        deterministic.fill_uninitialized_memory,
        torch.get_num_threads(),
    )
    assert after == before


def test_torch_settings_do_not_import_the_compiler():
    """torch.use_deterministic_algorithms imports torch._inductor (2-3 s); we do not."""
    code = textwrap.dedent(
        """
        import sys, torch
        from sparsetools.train.runtime import torch_settings
        with torch_settings(1, torch.device("cpu")):
            assert torch.are_deterministic_algorithms_enabled()
        print("inductor" if "torch._inductor" in sys.modules else "clean")
        """
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "clean"


# -- background checkpoint writing ----------------------------------------------------------------
def test_background_writer_saves_the_snapshot_taken_at_the_call(tmp_path):
    weights = torch.arange(6.0)
    obj = {"model": {"w": weights}, "opt": [{"step": torch.tensor(3)}], "note": "x"}
    writer = BackgroundWriter()
    writer.save(obj, tmp_path / "a.pt")
    weights.add_(100)  # training goes on changing the tensors at once
    writer.copy(tmp_path / "a.pt", tmp_path / "b.pt")
    writer.close()
    for name in ("a.pt", "b.pt"):
        back = torch.load(tmp_path / name, weights_only=True)
        assert torch.equal(back["model"]["w"], torch.arange(6.0))
        assert back["opt"][0]["step"].item() == 3 and back["note"] == "x"
    assert not list(tmp_path.glob(".tmp-*"))


def test_background_saves_route_save_torch_and_keep_the_order(tmp_path):
    with background_saves() as writer:
        for i in range(3):
            save_torch({"i": torch.tensor(i)}, tmp_path / "last.pt")
        copy_file(tmp_path / "last.pt", tmp_path / "best.pt")
        assert isinstance(writer, BackgroundWriter)
    # every file complete on leaving the block; the copy came after the last save
    assert torch.load(tmp_path / "last.pt", weights_only=True)["i"].item() == 2
    assert torch.load(tmp_path / "best.pt", weights_only=True)["i"].item() == 2
    # outside the block, writes are synchronous again
    save_torch({"i": torch.tensor(7)}, tmp_path / "now.pt")
    assert torch.load(tmp_path / "now.pt", weights_only=True)["i"].item() == 7


def test_a_failed_background_write_is_raised_and_leaves_nothing(tmp_path):
    (tmp_path / "file").write_text("in the way")
    target = tmp_path / "file" / "last.pt"  # its folder is a file
    with pytest.raises(OutputError), background_saves():
        save_torch({"w": torch.ones(3)}, target)
        copy_file(target, tmp_path / "best.pt")  # skipped after the failure
    assert not (tmp_path / "best.pt").exists()
    writer = BackgroundWriter()
    writer.save({"w": torch.ones(3)}, target)
    with pytest.raises(OutputError):
        writer.save({"w": torch.ones(3)}, tmp_path / "next.pt")  # raised before the next
    writer.close()
    assert not (tmp_path / "next.pt").exists() and not list(tmp_path.glob(".tmp-*"))


def test_an_error_in_the_block_still_waits_for_the_file(tmp_path):
    with pytest.raises(KeyError), background_saves():
        save_torch({"w": torch.zeros(1000, 1000)}, tmp_path / "last.pt")
        raise KeyError("training failed")
    assert torch.load(tmp_path / "last.pt", weights_only=True)["w"].shape == (1000, 1000)


def test_killed_during_a_background_write_the_old_file_stays_whole(tmp_path):
    """SIGKILL while the writer thread is busy: last.pt is the old or the new file, whole."""
    target = tmp_path / "last.pt"
    torch.save({"version": 1, "w": torch.zeros(4)}, target)
    code = textwrap.dedent(
        f"""
        import os, signal, torch
        from sparsetools.train.runtime import background_saves, save_torch
        with background_saves():
            save_torch({{"version": 2, "w": torch.ones(64, 1024, 1024)}}, {str(target)!r})
            print("queued", flush=True)
            os.kill(os.getpid(), signal.SIGKILL)
        """
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == -signal.SIGKILL and "queued" in r.stdout, r.stderr
    back = torch.load(target, weights_only=True)
    assert back["version"] in (1, 2)
    assert back["w"].shape == ((4,) if back["version"] == 1 else (64, 1024, 1024))
