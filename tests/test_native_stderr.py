"""What C libraries print on fd 2 is captured per block, through one sink per process."""

from __future__ import annotations

import os
import threading

import pytest

from sparsetools.io import _native
from sparsetools.io._native import native_stderr_captured


def _say(text: bytes) -> None:
    os.write(2, text)  # what libpng does: straight to the descriptor, past sys.stderr


def test_text_written_to_fd2_is_captured_and_not_printed(capfd):
    with native_stderr_captured() as got:
        _say(b"libpng error: Not enough   image data\n")
    assert got == ["libpng error: Not enough image data"]
    out, err = capfd.readouterr()
    assert err == "" and out == ""
    _say(b"after\n")  # fd 2 is restored after the block
    assert capfd.readouterr().err == "after\n"


def test_blocks_reuse_one_sink_and_each_sees_only_its_own_text(capfd, monkeypatch):
    made = []
    real = _native.tempfile.TemporaryFile
    monkeypatch.setattr(_native.tempfile, "TemporaryFile", lambda: made.append(1) or real())
    sinks = []
    with native_stderr_captured() as first:
        _say(b"one\n")
        sinks.append(os.fstat(2).st_ino)
    with native_stderr_captured() as second:
        sinks.append(os.fstat(2).st_ino)
    with native_stderr_captured() as third:
        _say(b"three\n")
        sinks.append(os.fstat(2).st_ino)
    assert (first, second, third) == (["one"], [""], ["three"])
    assert len(set(sinks)) == 1 and len(made) <= 1, "a new temporary file per block"
    assert capfd.readouterr().err == ""


def test_a_grown_sink_is_emptied_between_blocks(capfd, monkeypatch):
    monkeypatch.setattr(_native, "_SINK_MAX", 100)
    with native_stderr_captured():
        _say(b"x" * 300)
    with native_stderr_captured() as got:
        _say(b"short\n")
    assert got == ["short"]
    assert os.fstat(_native._sink.fileno()).st_size == len(b"short\n")
    capfd.readouterr()


def test_nested_and_threaded_blocks_restore_fd2_once_the_last_leaves(capfd):
    barrier = threading.Barrier(2)
    results = []

    def worker():
        with native_stderr_captured() as got:
            barrier.wait()
            barrier.wait()
        results.append(got)

    t = threading.Thread(target=worker)
    t.start()
    with native_stderr_captured() as mine:
        barrier.wait()  # both inside
        _say(b"both inside\n")
        barrier.wait()
    t.join()
    assert mine == ["both inside"]
    assert _native._users == 0 and _native._saved_fd is None
    _say(b"restored\n")
    assert capfd.readouterr().err.endswith("restored\n")


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork is POSIX")
def test_a_forked_child_makes_its_own_sink(capfd):
    with native_stderr_captured():
        _say(b"parent\n")
        parent_sink = os.fstat(2).st_ino
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # child: report whether it made a new sink and captured its own text
        try:
            with native_stderr_captured() as got:
                _say(b"child\n")
                own = os.fstat(2).st_ino
            ok = own != parent_sink and got == ["child"]
            os.write(w, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(w)
    answer = os.read(r, 1)
    os.close(r)
    os.waitpid(pid, 0)
    assert answer == b"1"
    with native_stderr_captured() as again:  # the parent's sink is unaffected
        _say(b"parent again\n")
        same = os.fstat(2).st_ino == parent_sink
    assert again == ["parent again"] and same
    assert capfd.readouterr().err == ""
