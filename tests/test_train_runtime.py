"""Training runtime: the thread default, torch settings and checkpoints written on a
background thread (issue 18). The DataLoader workers' bounds are tested in
tests/robustness/test_train_workers.py (issue 13)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import pytest
import torch

from sparsetools.errors import OutputError
from sparsetools.train import runtime
from sparsetools.train.runtime import (
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
    ("cores", "cap", "expected"),
    [
        (2, 8, 2),  # every CPU this process may use
        (16, 4, 4),  # OMP_NUM_THREADS / physical cores bound it
        (1, 8, 1),
        (0, 8, 1),  # never 0
        (4, 0, 1),
    ],
)
def test_default_threads_is_the_usable_cpus(cores, cap, expected):
    assert default_threads(cores=cores, cap=cap) == expected


def test_default_threads_reads_this_machine():
    n = default_threads()
    assert n == max(1, min(runtime.available_cores(), runtime._TORCH_DEFAULT_THREADS))
    assert resolve_threads(3) == 3 and resolve_threads(None) == n


def test_default_threads_do_not_depend_on_the_load():
    """Issue 23: the same command gives the same thread count (hence the same CPU results)
    however busy the machine is at the moment: with every CPU of this process held by
    another process, the default is what it is on an idle machine. (0.3-dev counted the idle
    cores over 0.2 s: it gave 1 here.)"""
    expected = max(1, min(runtime.available_cores(), runtime._TORCH_DEFAULT_THREADS))
    burn = "import time\nt = time.time()\nwhile time.time() - t < 20: pass\n"
    hogs = [
        subprocess.Popen([sys.executable, "-c", burn]) for _ in range(runtime.available_cores())
    ]
    try:
        time.sleep(0.5)  # the hogs are running
        assert [default_threads() for _ in range(3)] == [expected] * 3
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()


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
