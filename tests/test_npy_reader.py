"""``io.npy.load_npy`` decodes what ``np.load`` decodes, parses each distinct header once,
and refuses what it refused before."""

from __future__ import annotations

import io

import numpy as np
import pytest

from sparsetools.errors import FormatError
from sparsetools.io import npy


def _npy_bytes(arr, version=None) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, arr, version=version, allow_pickle=False)
    return buf.getvalue()


def _cases():
    rng = np.random.default_rng(7)
    yield rng.random((4, 5)).astype(np.float32)
    yield rng.random((4, 5)).astype(">f8")  # big-endian
    yield np.asfortranarray(rng.random((3, 7)))
    yield np.asfortranarray(rng.integers(0, 9, (2, 3, 4), dtype=np.uint16))
    yield rng.integers(-5, 5, (6,), dtype=np.int8)
    yield np.zeros((0, 5), np.float32)
    yield np.zeros((3, 0), np.uint16)
    yield np.array(3.5)
    yield np.array([b"ab", b"c"])
    yield np.zeros(3, dtype=[("u", "<u2"), ("d", "<f4")])


@pytest.mark.parametrize("version", [None, (1, 0), (2, 0), (3, 0)])
@pytest.mark.parametrize("case", range(10))
def test_load_npy_equals_np_load(case, version):
    arr = list(_cases())[case]
    data = _npy_bytes(arr, version)
    for _ in range(2):  # the second time from the parsed-header cache
        got = npy.load_npy(data, source="x.npy")
        want = np.load(io.BytesIO(data), allow_pickle=False)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert got.flags.f_contiguous == want.flags.f_contiguous
        assert got.tobytes(order="A") == want.tobytes(order="A")
        assert got.flags.writeable


def test_each_distinct_header_is_parsed_once(monkeypatch):
    calls = []
    real = npy._header
    monkeypatch.setattr(npy, "_header", lambda *a: calls.append(1) or real(*a))
    npy._parsed.clear()
    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    for k in range(5):
        assert np.array_equal(npy.load_npy(_npy_bytes(a + k), source="x"), a + k)
    assert len(calls) == 1
    npy.load_npy(_npy_bytes(a.astype(np.float64)), source="x")
    assert len(calls) == 2


def test_a_cached_header_still_checks_the_data_length():
    a = np.ones((4, 4), np.float32)
    good = _npy_bytes(a)
    npy.load_npy(good, source="x")  # now cached
    with pytest.raises(FormatError, match="truncated or corrupt"):
        npy.load_npy(good[:-4], source="x")
    with pytest.raises(FormatError, match="truncated or corrupt"):
        npy.load_npy(good + b"\0" * 4, source="x")


def test_bad_headers_are_refused_in_one_line():
    a = np.ones((2, 2), np.float32)
    good = _npy_bytes(a)
    obj = io.BytesIO()
    np.lib.format.write_array(obj, np.array([1, "a"], dtype=object), allow_pickle=True)
    for _ in range(2):  # refused from the cache too
        with pytest.raises(FormatError, match="object arrays"):
            npy.load_npy(obj.getvalue(), source="x")
    for bad in (b"", b"\x93NUMPY", b"not an npy file at all", good[:12],
                good[:6] + b"\x07\x00" + good[8:]):  # fmt: skip
        with pytest.raises(FormatError) as exc:
            npy.load_npy(bad, source="x.npy")
        assert "\n" not in str(exc.value) and str(exc.value).startswith("x.npy: ")
