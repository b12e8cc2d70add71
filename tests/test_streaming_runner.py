"""Issue 28: the frame runner's bookkeeping is O(1) per frame, and streaming changes nothing.

The journal index (io/frame_index.py), the on-disk result log (pipeline/batch.ResultLog), the
chunked lazy executors (pipeline/chunking.py), the compact source index (io/sources FileMap,
FrameList): each against the straightforward version it replaces, plus memory properties that
fail when a per-frame object is kept again.
"""

from __future__ import annotations

import json
import os
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from _pipeline_jobs import RandomInput, WriteRandom
from sparsetools.errors import FormatError, OutputError, ParameterError
from sparsetools.io.frame_index import FrameIndex, compact_journal, key_hash
from sparsetools.io.provenance import (
    FrameJournal,
    FrameRecord,
    iter_frame_records,
    read_frame_records,
    write_frame_records,
)
from sparsetools.io.sources import FrameKey
from sparsetools.io.sources.clouds import cloud_frames
from sparsetools.io.sources.frame import Frame, FrameList
from sparsetools.io.sources.tree import FileMap, index_tree
from sparsetools.pipeline import Batch, FrameTask, RunSpec, run_frames
from sparsetools.pipeline.batch import FrameResult, ResultLog
from sparsetools.pipeline.chunking import ChunkSizer, map_in_chunks, run_chunk
from sparsetools.pipeline.core import PLAN_CHUNK, TaskStream, _check_tasks


# -- the journal index -----------------------------------------------------------------------------
def _rec(key: str, n: int = 0) -> FrameRecord:
    return FrameRecord(key, {"data": f"{key}.bin"}, (), {"n": n})


def _journal(out: Path, lines: list[str]) -> Path:
    d = out / ".sparsetools"
    d.mkdir(parents=True, exist_ok=True)
    (d / "frames.jsonl").write_text("".join(lines))
    return d / "frames.jsonl"


def test_index_gives_what_reading_the_whole_journal_gives(tmp_path):
    # a key twice (the last line wins), a damaged line, a blank line, a key whose last line is
    # damaged (its earlier valid line wins, as read_frame_records does)
    lines = [
        _rec("b", 1).to_line() + "\n",
        _rec("a", 1).to_line() + "\n",
        "\n",
        '{"key": "c", "outp\n',
        _rec("b", 2).to_line() + "\n",
        _rec("c", 5).to_line() + "\n",
        '{"key": "c", "outputs": 3}\n',
        _rec("d", 1).to_line(),
    ]  # fmt: skip  (the last line has no newline)
    _journal(tmp_path, lines)
    whole = read_frame_records(tmp_path)
    index = FrameIndex(tmp_path)
    try:
        assert len(index) == len(whole) == 4
        for key, rec in whole.items():
            assert index.get(key) == rec
        assert index.get("zz") is None and index.get("") is None
        assert index.end == (tmp_path / ".sparsetools" / "frames.jsonl").stat().st_size
    finally:
        index.close()


def test_compaction_equals_the_rewrite_of_all_records(tmp_path):
    old = {k: _rec(k, i) for i, k in enumerate(["s/003", "s/001", "t/000", "s/002"])}
    write_frame_records(tmp_path, old)
    index = FrameIndex(tmp_path)
    with FrameJournal(tmp_path) as journal:  # this run: one new frame, one redone
        journal.append(_rec("s/000", 9))
        journal.append(_rec("s/002", 7))
    compact_journal(tmp_path, index, keep_old=True, dropped={"t/000"})
    index.close()
    expected = {k: v for k, v in old.items() if k != "t/000"}
    expected.update({"s/000": _rec("s/000", 9), "s/002": _rec("s/002", 7)})
    text = (tmp_path / ".sparsetools" / "frames.jsonl").read_text()
    assert text == "".join(expected[k].to_line() + "\n" for k in sorted(expected))


def test_compaction_with_overwrite_keeps_only_this_runs_lines(tmp_path):
    write_frame_records(tmp_path, {"a": _rec("a"), "b": _rec("b")})
    index = FrameIndex(tmp_path)
    with FrameJournal(tmp_path) as journal:
        journal.append(_rec("c", 3))
    compact_journal(tmp_path, index, keep_old=False)
    index.close()
    assert list(read_frame_records(tmp_path)) == ["c"]


def test_compaction_of_nothing_removes_the_journal(tmp_path):
    write_frame_records(tmp_path, {"a": _rec("a")})
    index = FrameIndex(tmp_path)
    compact_journal(tmp_path, index, keep_old=True, dropped={"a"})
    index.close()
    assert not (tmp_path / ".sparsetools" / "frames.jsonl").exists()


def test_appended_lines_after_a_line_cut_short_are_kept(tmp_path):
    # a crash left the last line without its newline: this run's first line lands on it
    _journal(tmp_path, [_rec("a").to_line() + "\n", '{"key": "b", "outputs": {"da'])
    index = FrameIndex(tmp_path)
    with FrameJournal(tmp_path) as journal:
        journal.append(_rec("b", 4))
    compact_journal(tmp_path, index, keep_old=True)
    index.close()
    # the glued line is damaged: b is recomputed next time, a is kept, nothing is invented
    assert set(read_frame_records(tmp_path)) <= {"a", "b"} and "a" in read_frame_records(tmp_path)


def test_a_hash_clash_never_gives_another_frames_record(tmp_path, monkeypatch):
    import sparsetools.io.frame_index as fi

    monkeypatch.setattr(fi, "key_hash", lambda key: 1)  # every key clashes
    write_frame_records(tmp_path, {"a": _rec("a", 1), "b": _rec("b", 2)})
    index = fi.FrameIndex(tmp_path)
    try:
        got = [index.get("a"), index.get("b")]
        # one of them is lost (recomputed), none is the other's
        assert got.count(None) == 1
        assert all(r is None or r.key == k for r, k in zip(got, "ab", strict=True))
    finally:
        index.close()


# -- the result log ----------------------------------------------------------------------------------
@pytest.mark.parametrize("on_disk", [False, True])
def test_result_log_reads_back_in_task_order(tmp_path, on_disk):
    log = ResultLog(5, folder=tmp_path if on_disk else None)
    results = [
        FrameResult("f3", True, {"x": 3}),
        FrameResult("f0", True, {"x": 0.5}, skipped=True),
        FrameResult("f4", False, error="bad", detail="trace"),
        FrameResult("f1", True, {"x": np.float32(1.5)}, recomputed=True),
    ]
    for pos, r in zip([3, 0, 4, 1], results, strict=True):
        log.add(pos, r)
    got = list(log)
    assert [r.frame_id for r in got] == ["f0", "f1", "f3", "f4"]
    assert got[1].stats == {"x": 1.5} and got[1].recomputed and got[0].skipped
    assert got[3].error == "bad" and got[3].detail == "trace" and not got[3].ok
    assert [log.count(s) for s in ("done", "resumed", "failed", "recomputed")] == [2, 1, 1, 1]
    if on_disk:
        assert list(tmp_path.iterdir()) == []  # an unnamed file: nothing left in the folder
    log.close()


def test_summary_lists_equal_the_runs_results(tmp_path):
    srcs = [tmp_path / f"in{i}.dat" for i in range(7)]
    for i, p in enumerate(srcs):
        p.write_bytes(bytes([i]) * 8)
    out = tmp_path / "o"

    def tasks():
        return [FrameTask(FrameKey("", f"{i:03d}"), RandomInput(str(s)),
                          {"data": out / f"{i:03d}.bin"}, (s,)) for i, s in enumerate(srcs)]  # fmt: skip

    spec = RunSpec("t", out, {"seed": 1})
    run_frames(WriteRandom(), tasks()[:4], spec=spec)
    srcs[1].write_bytes(b"changed!")
    s = run_frames(WriteRandom(bad=("005",)), tasks(), spec=spec, batch=Batch(on_error="skip"))
    assert [r.frame_id for r in s.results] == [f"{i:03d}" for i in range(7)]
    assert [r.frame_id for r in s.resumed] == ["000", "002", "003"]
    assert [r.frame_id for r in s.done] == ["001", "004", "006"]
    assert [r.frame_id for r in s.recomputed] == ["001"]
    assert [r.frame_id for r in s.failed] == ["005"]
    assert s.counts() == {"frames": 7, "processed": 3, "skipped_existing": 3, "recomputed": 1,
                          "failed": 1}  # fmt: skip
    # the statistics of up-to-date frames come from the record: the same as when computed
    first = {r.frame_id: r.stats["sum"] for r in run_frames(
        WriteRandom(), tasks(), batch=Batch(overwrite=True), spec=spec).done}  # fmt: skip
    again = {r.frame_id: r.stats["sum"] for r in run_frames(WriteRandom(), tasks(), spec=spec).ok}
    assert again == pytest.approx(first)


# -- checks over every task ----------------------------------------------------------------------------
def _task(fid, out, src=None):
    return FrameTask(FrameKey.parse(fid), None, {"data": Path(out)}, () if src is None else (src,))


def test_checks_name_the_same_pair_as_before(tmp_path):
    t = [_task("a", tmp_path / "1"), _task("b", tmp_path / "2"), _task("a", tmp_path / "3")]
    with pytest.raises(ParameterError, match="same frame id: a"):
        _check_tasks(t)
    t = [_task("a", tmp_path / "1"), _task("b", tmp_path / "2"), _task("c", tmp_path / "1")]
    with pytest.raises(ParameterError, match=r"frames a \(a\) and c \(c\) would both write"):
        _check_tasks(t)
    t = [_task("a", tmp_path / "1", src=tmp_path / "2"), _task("b", tmp_path / "2")]
    with pytest.raises(OutputError, match="would replace an input"):
        _check_tasks(t)
    _check_tasks([_task(f"s/{i}", tmp_path / f"{i}") for i in range(3000)])  # no clash


def test_hash_clashes_alone_refuse_nothing(tmp_path, monkeypatch):
    import sparsetools.pipeline.core as core

    monkeypatch.setattr(core, "key_hash", lambda key: 5)
    core._check_tasks([_task(f"f{i}", tmp_path / f"{i}") for i in range(50)])


def test_task_stream_is_the_tasks_of_all_frames_in_chunks(tmp_path):
    from sparsetools.pipeline.project import ProjectJob, ProjectSettings

    frames = [Frame(FrameKey(f"s{i % 3}", f"{i:04d}"), cloud=tmp_path / f"{i}.bin",
                    calib=tmp_path / "c.txt") for i in range(25)]  # fmt: skip
    job = ProjectJob(ProjectSettings(image_size=(64, 32)))
    whole = job.tasks(frames, tmp_path / "o")
    assert list(TaskStream(job, frames, tmp_path / "o", chunk=4)) == whole
    assert list(TaskStream(job, frames, tmp_path / "o")) == whole
    assert PLAN_CHUNK >= 256


# -- chunks and laziness ----------------------------------------------------------------------------------
def test_chunk_sizer_targets_the_work_and_keeps_workers_busy():
    s = ChunkSizer(10_000, 2, target_seconds=0.25, first=8, most=4096, balance=2)
    assert s.next_size() == 8
    s.observe(8, 0.016)  # 2 ms per frame -> 125 frames make 0.25 s
    assert s.next_size() == 125
    s.observe(100, 10.0)  # slow frames: one at a time
    assert s.next_size() == 3
    s = ChunkSizer(100, 2, target_seconds=10.0, most=4096, balance=2)
    s.observe(4, 0.004)
    assert s.next_size() == 25  # capped: every worker gets 2 chunks
    assert ChunkSizer(10, 4, target_seconds=1.0, fixed=7).next_size() == 7


def test_chunk_sizer_shrinks_the_last_chunks():
    """Guided self-scheduling: near the end a chunk takes at most a (2 x workers)-th of the
    frames not yet handed out, so no worker is left with a whole chunk while the other idles."""
    s = ChunkSizer(1000, 2, target_seconds=0.25, first=8, most=4096, balance=2)
    s.took(8)
    s.observe(8, 0.008)  # 1 ms per frame: 250 frames make 0.25 s; the cap is 1000 / 4
    assert s.next_size() == 248  # ceil(992 / 4)
    s.took(892)
    assert s.next_size() == 25  # 100 left: ceil(100 / 4)
    s.took(99)
    assert s.next_size() == 1
    s.took(1)
    assert s.next_size() == 1  # never 0, even past the estimate (n_items is an upper bound)
    fixed = ChunkSizer(10, 4, target_seconds=1.0, fixed=7)
    fixed.took(9)
    assert fixed.next_size() == 7


def test_map_in_chunks_hands_out_every_item_once_in_shrinking_tail_chunks():
    sizes = []
    sizer = ChunkSizer(400, 2, target_seconds=0.05, first=8, most=4096, balance=2)

    def submit(chunk):
        sizes.append(len(chunk))
        return _Now(([x for x in chunk], 0.001 * len(chunk)))  # 1 ms of work per frame

    out = list(map_in_chunks(iter(range(400)), submit=submit,
                             wait_any=lambda fs: [next(iter(fs))], sizer=sizer, window=4))  # fmt: skip
    assert sorted(out) == list(range(400))
    assert sum(sizes) == 400
    assert max(sizes) == 50  # 0.05 s of 1 ms frames
    assert sizes[-3:] == sorted(sizes[-3:], reverse=True) and sizes[-1] <= 2


class _Now:
    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


def test_map_in_chunks_takes_items_only_as_chunks_complete():
    taken = []

    def items():
        for i in range(100):
            taken.append(i)
            yield i

    sizer = ChunkSizer(100, 1, target_seconds=0.0, fixed=5)
    done = []
    gen = map_in_chunks(items(), submit=lambda c: _Now(run_chunk(lambda x: x * x, c)),
                        wait_any=lambda fs: [next(iter(fs))], sizer=sizer, window=2)  # fmt: skip
    first = next(gen)
    assert len(taken) <= 10  # two chunks of 5 in flight, not the 100 items
    done = [first, *gen]
    assert sorted(done) == [i * i for i in range(100)]


@pytest.mark.parametrize("workers", [1, 2])
def test_pool_results_do_not_depend_on_chunks(tmp_path, workers):
    from sparsetools.pipeline.executors import LocalExecutor, SerialExecutor

    ex = SerialExecutor() if workers == 1 else LocalExecutor(2, n_items=37)
    got = sorted(ex.map(abs, iter(range(-18, 19))))
    assert got == sorted(abs(i) for i in range(-18, 19))


# -- the compact source index -------------------------------------------------------------------------------
def _tree(root: Path) -> None:
    for seq in ("b", "a", "a-b", "a/x"):
        d = root / seq
        d.mkdir(parents=True, exist_ok=True)
        for name in ("0002.bin", "0001.bin", "0001_sweep1.bin", "x_conf.bin", ".hidden.bin"):
            (d / name).write_bytes(b"\0" * 16)
    (root / "0009.bin").write_bytes(b"\0" * 16)


def _dict_index(root: Path) -> dict:
    """What the index was: every cloud file by (sequence, stem), companions left out."""
    out = {}
    for p in sorted(root.rglob("*.bin")):
        if p.name.startswith("."):
            continue
        rel = p.parent.relative_to(root).as_posix()
        out[FrameKey("" if rel == "." else rel, p.name[:-4])] = p
    return {k: v for k, v in sorted(out.items())
            if not (k.frame.endswith("_sweep1") and FrameKey(k.sequence, k.frame[:-7]) in out)}  # fmt: skip


def test_file_map_is_the_dict_it_replaces(tmp_path):
    _tree(tmp_path)
    files = index_tree(tmp_path, (".bin",), option="CLOUD").files
    assert isinstance(files, FileMap)
    expected = _dict_index(tmp_path)
    assert list(files) == list(expected) and list(files.items()) == list(expected.items())
    for k, p in expected.items():
        assert k in files and files[k] == p and files.get(k) == p
    assert FrameKey("a", "0003") not in files and "a/0001" not in files
    with pytest.raises(KeyError):
        files[FrameKey("zz", "0001")]


def test_two_files_of_one_frame_are_refused_naming_both(tmp_path):
    (tmp_path / "x.bin").write_bytes(b"")
    (tmp_path / "x.npy").write_bytes(b"")
    with pytest.raises(FormatError, match=r"x\.bin and .*x\.npy are the same frame 'x'"):
        index_tree(tmp_path, (".bin", ".npy"), option="CLOUD")


def test_frame_list_gives_the_frames_a_list_gives(tmp_path):
    _tree(tmp_path)
    calib = tmp_path.parent / "calib.txt"
    calib.write_text("P2: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    frames = cloud_frames([tmp_path], calib=calib)
    assert isinstance(frames, FrameList)
    expected = [Frame(key=k, cloud=p, calib=calib) for k, p in _dict_index(tmp_path).items()]
    assert list(frames) == expected and frames[2:5] == expected[2:5]
    assert frames[-1] == expected[-1] and len(frames) == len(expected)
    with pytest.raises(IndexError):
        frames[len(expected)]
    # two inputs: the list the matching builds, the same frames
    two = cloud_frames([tmp_path / "a" / "0001.bin", tmp_path / "b" / "0002.bin"], calib=calib)
    assert not isinstance(two, FrameList)
    assert two == [
        Frame(FrameKey("", "0001"), cloud=tmp_path / "a" / "0001.bin", calib=calib),
        Frame(FrameKey("", "0002"), cloud=tmp_path / "b" / "0002.bin", calib=calib),
    ]


# -- memory: O(1) per frame -----------------------------------------------------------------------------------
class _Nothing:
    def __call__(self, task):
        return {"n": 1}


def _held_per_frame(n: int, tmp_path: Path, spec: bool) -> float:
    """Bytes the runner still holds per frame when it returns (the summary alive)."""
    out = tmp_path / f"o{n}"
    tasks = TaskStream(_JobOf(out), list(range(n)), out, chunk=512)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    s = run_frames(_Nothing(), tasks, spec=RunSpec("t", out, {}) if spec else None)
    held = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    assert s.counts()["processed"] == n
    return held / n


class _JobOf:
    def __init__(self, out):
        self.out = out

    def tasks(self, frames, out_dir):
        # checked keys: FrameKey's check interns the name (pathlib), which grows Python's table
        # of interned strings, a cost of the test's keys and not of the runner
        return [FrameTask(FrameKey.checked("s", f"{i:07d}"), None, {}, ()) for i in frames]


def test_the_runner_holds_bytes_not_objects_per_frame(tmp_path):
    # the result log is on disk and the journal read through 16-byte entries: what is still held
    # at the end is its 9 bytes per frame plus a few of the allocator's (measured 12-16); any
    # per-frame object kept (a FrameResult alone is ~400 bytes, a key string ~60) fails this
    per_frame = _held_per_frame(20_000, tmp_path, spec=True)
    assert per_frame < 40, per_frame
    # without an output folder the log keeps each result's JSON line in memory (~100 bytes)
    assert _held_per_frame(20_000, tmp_path, spec=False) < 160


def test_journal_of_a_resumed_run_equals_an_uninterrupted_ones(tmp_path):
    # streaming compaction: frames done in two runs give the journal one run gives
    srcs = []
    for i in range(30):
        p = tmp_path / "in" / f"{i:03d}.dat"
        p.parent.mkdir(exist_ok=True)
        p.write_bytes(bytes([i]) * 4)
        srcs.append(p)

    def tasks(out, sel):
        return [FrameTask(FrameKey("q", p.stem), RandomInput(str(p)), {"data": out / f"{p.stem}.bin"},
                          (p,)) for p in sel]  # fmt: skip

    a, b = tmp_path / "a", tmp_path / "b"
    run_frames(WriteRandom(), tasks(a, srcs), spec=RunSpec("t", a, {}))
    run_frames(WriteRandom(), tasks(b, srcs[::3]), spec=RunSpec("t", b, {}))
    run_frames(WriteRandom(), tasks(b, srcs), spec=RunSpec("t", b, {}), batch=Batch(workers=2))
    ja, jb = (p / ".sparsetools" / "frames.jsonl" for p in (a, b))
    strip = [json.loads(x)["stats"] for x in ja.read_text().splitlines()]
    assert len(strip) == 30
    keys = lambda p: [json.loads(x)["key"] for x in p.read_text().splitlines()]  # noqa: E731
    assert keys(ja) == keys(jb) == sorted(keys(ja))
    sums = lambda out: [r.stats["sum"] for r in iter_frame_records(out)]  # noqa: E731
    assert sums(a) == sums(b)
    # a no-op rerun leaves the journal as it is (no rewrite)
    before = os.stat(jb)
    run_frames(WriteRandom(), tasks(b, srcs), spec=RunSpec("t", b, {}))
    assert os.stat(jb).st_ino == before.st_ino and os.stat(jb).st_mtime_ns == before.st_mtime_ns
    assert key_hash("q/000") == key_hash("q/000")


@pytest.mark.parametrize("root", ["/a/b", "a/b/", ".", "/a//b/./c", Path("/x/y")])
def test_frame_path_is_the_pathlib_join(root):
    # FrameKey.path parses one joined string (speed); it must equal joining Path parts
    for seq in ("", "s", "s/t"):
        for prefix in ("", "calib"):
            old = Path(root)
            old = old / prefix if prefix else old
            old = old / seq if seq else old
            got = FrameKey(seq, "000001").path(root, ".png", prefix=prefix)
            assert got == old / "000001.png" and str(got) == str(old / "000001.png")
