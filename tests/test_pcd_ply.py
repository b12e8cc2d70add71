"""The native PCD / PLY readers and writers (issue 28): the same arrays as Open3D's tensor API
gave (the reader before 0.4, written here as the reference), on files Open3D wrote in every
variant, on hand-made files of every field type, and on the real nuScenes radar files; the
documented differences where Open3D loses data; LZF against an encoder written here; and
nothing of it needs Open3D."""

from __future__ import annotations

import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sparsetools.errors import DependencyError, FormatError
from sparsetools.io.lzf import lzf_decompress
from sparsetools.io.pcd import read_pcd
from sparsetools.io.ply import read_ply_vertices
from sparsetools.io.pointcloud import read_points, write_points

o3d = pytest.importorskip("open3d")  # installed by `make test` (the open3d extra)
o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

REAL_RADAR = Path(__file__).resolve().parents[2] / "shared/data/real/nuscenes-radar"
NAMES = {3: "intensity", 4: "ring"}


def open3d_read(path) -> np.ndarray:
    """The 0.3 reader: Open3D's tensor cloud, positions then the other keys sorted, finite rows."""
    pcd = o3d.t.io.read_point_cloud(str(path))
    cols = [pcd.point["positions"].numpy().astype(np.float32).reshape(-1, 3)]
    for key in sorted(k for k in pcd.point if k != "positions"):
        a = pcd.point[key].numpy().astype(np.float32)
        cols.append(a.reshape(a.shape[0], -1))
    points = np.hstack(cols)
    return points[np.isfinite(points).all(axis=1)]


def open3d_write(path, points, **kw) -> None:
    pcd = o3d.t.geometry.PointCloud()
    pcd.point["positions"] = o3d.core.Tensor(np.ascontiguousarray(points[:, :3]))
    for i in range(3, points.shape[1]):
        pcd.point[NAMES.get(i, f"attr{i}")] = o3d.core.Tensor(
            np.ascontiguousarray(points[:, i : i + 1])
        )
    assert o3d.t.io.write_point_cloud(str(path), pcd, **kw)


def cloud(n, c, seed=0, nan_rows=0):
    rng = np.random.default_rng(seed)
    scale = np.r_[30.0, 30.0, 2.0, np.full(c - 3, 10.0)]
    pts = (rng.normal(size=(n, c)) * scale).astype(np.float32)
    pts[:nan_rows, 1] = np.nan
    return pts


# -- every variant Open3D writes ------------------------------------------------------------------
VARIANTS = {
    "pcd-binary": (".pcd", {"write_ascii": False}),
    "pcd-ascii": (".pcd", {"write_ascii": True}),
    "pcd-binary_compressed": (".pcd", {"write_ascii": False, "compressed": True}),
    "ply-binary": (".ply", {"write_ascii": False}),
    "ply-ascii": (".ply", {"write_ascii": True}),
}


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("columns", [3, 4, 5, 7])
def test_native_reader_equals_open3d_on_files_open3d_wrote(tmp_path, variant, columns):
    suffix, kw = VARIANTS[variant]
    path = tmp_path / f"c{suffix}"
    open3d_write(path, cloud(2000, columns, seed=columns, nan_rows=3), **kw)
    got = read_points(path)
    want = open3d_read(path)
    assert got.shape == (1997, columns) and got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
def test_an_empty_cloud_round_trips_as_zero_rows(tmp_path, suffix):
    # (Open3D refuses to write an empty cloud; an empty PCD/PLY is a valid file all the same)
    write_points(tmp_path / f"e{suffix}", np.zeros((0, 4), np.float32))
    assert read_points(tmp_path / f"e{suffix}").shape == (0, 4)
    (tmp_path / "a.pcd").write_bytes(pcd_bytes(XYZ, [], "ascii"))
    assert read_points(tmp_path / "a.pcd").shape == (0, 3)


@pytest.mark.real
def test_native_reader_equals_open3d_on_the_real_radar_files():
    files = sorted(REAL_RADAR.rglob("*.pcd"))
    if not files:
        pytest.skip(f"{REAL_RADAR} absent")
    from sparsetools.io.pointcloud import _read_pcd_ply

    for f in files:
        got = _read_pcd_ply(f)  # the generic path, not the radar reader
        assert got.shape[1] == 18
        np.testing.assert_array_equal(got, open3d_read(f))
        rec, header = read_pcd(f)
        assert header.data == "binary" and rec.shape[0] == header.points


# -- hand-made files of every field type --------------------------------------------------------
def pcd_bytes(fields, rows, kind="binary"):
    """A PCD of ``fields`` = [(name, 'F'|'I'|'U', size, count)] and structured ``rows``."""
    dtype = np.dtype(
        [(f, f"<{t.lower()}{s}", (c,)) if c > 1 else (f, f"<{t.lower()}{s}")
         for f, t, s, c in fields]
    )  # fmt: skip
    rec = np.array(rows, dtype=dtype)
    head = (
        f"VERSION 0.7\nFIELDS {' '.join(f[0] for f in fields)}\n"
        f"SIZE {' '.join(str(f[2]) for f in fields)}\nTYPE {' '.join(f[1] for f in fields)}\n"
        f"COUNT {' '.join(str(f[3]) for f in fields)}\nWIDTH {len(rows)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(rows)}\nDATA {kind}\n"
    ).encode()
    if kind == "binary":
        return head + rec.tobytes()
    lines = []
    for r in rec:
        values = []
        for name in dtype.names:
            values.extend(np.atleast_1d(r[name]).tolist())
        lines.append(" ".join(repr(v) for v in values))
    return head + ("\n".join(lines) + "\n").encode()


XYZ = [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 4, 1)]
TYPES = [("F", 4), ("F", 8), ("I", 1), ("I", 2), ("I", 4), ("U", 1), ("U", 2), ("U", 4)]


@pytest.mark.parametrize("kind", ["binary", "ascii"])
@pytest.mark.parametrize(("t", "size"), TYPES)
def test_every_pcd_field_type_reads_as_open3d_reads_it(tmp_path, kind, t, size):
    value = {"F": 1.5, "I": -7, "U": 200}[t]
    rows = [(1.0, 2.0, 3.0, value), (4.0, -5.0, 6.5, 0)]
    path = tmp_path / "t.pcd"
    path.write_bytes(pcd_bytes([*XYZ, ("v", t, size, 1)], rows, kind))
    got = read_points(path)
    np.testing.assert_array_equal(got, open3d_read(path))
    assert got[0].tolist() == [1.0, 2.0, 3.0, value]


def test_pcd_packed_colours_and_normals_take_open3ds_names_and_order(tmp_path):
    rgb = struct.unpack("<f", struct.pack("<I", 0x00FF8040))[0]
    fields = [*XYZ, ("rgb", "F", 4, 1), ("normal_x", "F", 4, 1), ("normal_y", "F", 4, 1),
              ("normal_z", "F", 4, 1), ("curvature", "F", 4, 1), ("label", "U", 4, 1)]  # fmt: skip
    path = tmp_path / "c.pcd"
    path.write_bytes(pcd_bytes(fields, [(1, 2, 3, rgb, 0, 0, 1, 0.25, 9)]))
    got = read_points(path)
    np.testing.assert_array_equal(got, open3d_read(path))
    # colors (r, g, b), curvature, label, normals: Open3D's names, sorted
    assert got[0].tolist() == [1, 2, 3, 255, 128, 64, 0.25, 9, 0, 0, 1]


def test_fields_in_any_order_put_x_y_z_first(tmp_path):
    fields = [("intensity", "F", 4, 1), ("z", "F", 4, 1), ("x", "F", 4, 1), ("y", "F", 4, 1)]
    path = tmp_path / "o.pcd"
    path.write_bytes(pcd_bytes(fields, [(0.5, 3.0, 1.0, 2.0)]))
    assert read_points(path)[0].tolist() == [1.0, 2.0, 3.0, 0.5]
    np.testing.assert_array_equal(read_points(path), open3d_read(path))
    # x, y, z of different types: read right (Open3D finds no positions in such a PCD, and
    # reads garbage from such a PLY)
    fields[2] = ("x", "F", 8, 1)
    path.write_bytes(pcd_bytes(fields, [(0.5, 3.0, 1.0, 2.0)]))
    assert read_points(path)[0].tolist() == [1.0, 2.0, 3.0, 0.5]
    (tmp_path / "m.ply").write_bytes(
        ply_bytes([("x", "double"), ("y", "float"), ("z", "float")], [(1.5, 2, 3)])
    )
    assert read_points(tmp_path / "m.ply")[0].tolist() == [1.5, 2, 3]


def test_where_open3d_loses_data_the_native_reader_keeps_it(tmp_path):
    # COUNT > 1: every value (Open3D kept the first); PCL's "_" padding: skipped
    fields = [*XYZ, ("hist", "F", 4, 3), ("_", "U", 1, 4), ("w", "F", 4, 1)]
    path = tmp_path / "h.pcd"
    path.write_bytes(pcd_bytes(fields, [(1, 2, 3, (7, 8, 9), (0, 0, 0, 0), 5)]))
    assert read_points(path)[0].tolist() == [1, 2, 3, 7, 8, 9, 5]
    assert open3d_read(path).shape[1] == 6  # x y z, hist[0], _[0], w
    # PLY char / short / ushort / uint: kept, with their values (Open3D dropped them)
    for ply_type, value in (("char", -3), ("short", -300), ("ushort", 60000), ("uint", 70000)):
        p = tmp_path / f"{ply_type}.ply"
        p.write_bytes(ply_bytes([("x", "float"), ("y", "float"), ("z", "float"),
                                 ("s", ply_type)], [(1, 2, 3, value)]))  # fmt: skip
        assert read_points(p)[0].tolist() == [1, 2, 3, value]
        assert open3d_read(p).shape[1] == 3


# -- PLY ------------------------------------------------------------------------------------------
PLY_CODES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4",
             "uint": "u4", "float": "f4", "double": "f8"}  # fmt: skip


def ply_bytes(props, rows, fmt="binary_little_endian", before=(), after=()):
    """A PLY whose vertex element has ``props``; ``before``/``after``: (header lines, body)."""
    order = ">" if fmt == "binary_big_endian" else "<"
    rec = np.array(rows, dtype=[(p, order + PLY_CODES[t]) for p, t in props])
    head = f"ply\nformat {fmt} 1.0\ncomment made by the tests\n"
    head += "".join(h for h, _ in before)
    head += f"element vertex {len(rows)}\n" + "".join(f"property {t} {p}\n" for p, t in props)
    head += "".join(h for h, _ in after) + "end_header\n"
    if fmt == "ascii":
        body = "".join(" ".join(repr(v) for v in r.tolist()) + "\n" for r in rec).encode()
    else:
        body = rec.tobytes()
    return head.encode() + b"".join(b for _, b in before) + body + b"".join(b for _, b in after)


PLY_PROPS = [("x", "float"), ("y", "float"), ("z", "float"), ("red", "uchar"),
             ("green", "uchar"), ("blue", "uchar"), ("nx", "float"), ("ny", "float"),
             ("nz", "float"), ("label", "int"), ("intensity", "float")]  # fmt: skip
PLY_ROWS = [(1.5, 2, 3, 255, 128, 64, 0, 0, 1, -2, 0.5), (4, 5, 6, 1, 2, 3, 1, 0, 0, 7, 0.25)]


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply_of_every_format_reads_as_open3d_reads_it(tmp_path, fmt):
    path = tmp_path / "v.ply"
    path.write_bytes(ply_bytes(PLY_PROPS, PLY_ROWS, fmt))
    got = read_points(path)
    np.testing.assert_array_equal(got, open3d_read(path))
    # colors, intensity, label, normals: Open3D's names, sorted
    assert got[0].tolist() == [1.5, 2, 3, 255, 128, 64, 0.5, -2, 0, 0, 1]


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_ply_elements_around_the_vertices_are_skipped(tmp_path, fmt):
    order = "<"
    cam = np.array([(1.0, 2.0)], dtype=[("a", order + "f4"), ("b", order + "f4")])
    before = ("element camera 1\nproperty float a\nproperty float b\n",
              cam.tobytes() if fmt != "ascii" else b"1.0 2.0\n")  # fmt: skip
    faces = np.array([(3, (0, 1, 1))], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    after = ("element face 1\nproperty list uchar int vertex_indices\n",
             faces.tobytes() if fmt != "ascii" else b"3 0 1 1\n")  # fmt: skip
    path = tmp_path / "m.ply"
    path.write_bytes(ply_bytes(PLY_PROPS[:3], [(1, 2, 3), (4, 5, 6)], fmt, [before], [after]))
    np.testing.assert_array_equal(read_points(path), [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(read_points(path), open3d_read(path))


def test_unsupported_ply_layouts_are_one_clear_error(tmp_path):
    faces = ("element face 1\nproperty list uchar int vertex_indices\n", b"\x01\x00\x00\x00\x00")
    path = tmp_path / "f.ply"
    path.write_bytes(ply_bytes(PLY_PROPS[:3], [(1, 2, 3)], before=[faces]))
    with pytest.raises(FormatError, match="list element before the vertices"):
        read_points(path)
    path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\n"
        b"property float y\nproperty float z\nproperty list uchar int idx\nend_header\n"
        + b"\x00"
        * 17
    )
    with pytest.raises(FormatError, match="list properties"):
        read_points(path)


def test_a_truncated_or_miscounted_body_is_refused(tmp_path):
    data = ply_bytes(PLY_PROPS[:3], [(1, 2, 3), (4, 5, 6)])
    (tmp_path / "t.ply").write_bytes(data[:-1])
    with pytest.raises(FormatError, match="truncated"):
        read_points(tmp_path / "t.ply")
    ascii_data = ply_bytes(PLY_PROPS[:3], [(1, 2, 3), (4, 5, 6)], "ascii")
    (tmp_path / "a.ply").write_bytes(ascii_data.replace(b"4.0 5.0 6.0", b"4.0 5.0"))
    with pytest.raises(FormatError, match="ascii PLY"):
        read_points(tmp_path / "a.ply")
    pcd = pcd_bytes(XYZ, [(1, 2, 3), (4, 5, 6)], "ascii")
    (tmp_path / "a.pcd").write_bytes(pcd.replace(b"4.0 5.0 6.0", b"4.0 5.0 6.0 7.0"))
    with pytest.raises(FormatError, match="ascii PCD"):
        read_points(tmp_path / "a.pcd")
    (tmp_path / "b.pcd").write_bytes(pcd.replace(b"4.0 5.0", b"4.0 five"))
    with pytest.raises(FormatError, match="ascii PCD field 'y'"):
        read_points(tmp_path / "b.pcd")


# -- LZF ------------------------------------------------------------------------------------------
def lzf_encode(data: bytes) -> bytes:
    """A small LZF encoder, independent of the decoder: greedy matches of >= 3 bytes found by
    a dictionary of the last position of every 3-byte prefix, literal runs of <= 32 bytes."""
    out, literal, last = bytearray(), bytearray(), {}
    i = 0

    def flush():
        while literal:
            chunk = literal[:32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
            del literal[:32]

    while i < len(data):
        key = data[i : i + 3]
        ref = last.get(key) if len(key) == 3 else None
        if ref is not None and i - ref - 1 < 8192:
            length = 3
            while (
                i + length < len(data) and length < 264 and data[ref + length] == data[i + length]
            ):
                length += 1
            flush()
            off = i - ref - 1
            n = length - 2
            if n < 7:
                out.append((n << 5) | (off >> 8))
            else:
                out.extend([(7 << 5) | (off >> 8), n - 7])
            out.append(off & 255)
            for k in range(i, i + length):
                last[data[k : k + 3]] = k
            i += length
        else:
            if len(key) == 3:
                last[key] = i
            literal.append(data[i])
            i += 1
    flush()
    return bytes(out)


@pytest.mark.parametrize("seed", range(4))
def test_lzf_decodes_what_an_independent_encoder_encoded(seed):
    rng = np.random.default_rng(seed)
    pieces = [rng.integers(0, 4, 300).astype(np.uint8).tobytes(), b"\x00" * 1000,
              rng.integers(0, 256, 200).astype(np.uint8).tobytes(), b"ab" * 400]  # fmt: skip
    data = b"".join(pieces[k] for k in rng.permutation(4))
    packed = lzf_encode(data)
    assert len(packed) < len(data)  # back-references were made, overlapping ones included
    assert lzf_decompress(packed, len(data)) == data


def test_corrupt_lzf_streams_are_refused_never_read_out_of_bounds():
    with pytest.raises(FormatError, match="outside"):
        lzf_decompress(bytes([0x20, 0x05]), 10)  # a reference before the output's start
    with pytest.raises(FormatError, match="outside"):
        lzf_decompress(bytes([0x05, 1, 2]), 10)  # a literal run past the stream's end
    with pytest.raises(FormatError, match="outside"):
        lzf_decompress(bytes([0x02, 1, 2, 3, 0x20, 0x00]), 4)  # past the declared size
    with pytest.raises(FormatError, match="expands to 3 bytes"):
        lzf_decompress(bytes([0x02, 1, 2, 3]), 5)
    with pytest.raises(FormatError, match="outside"):
        lzf_decompress(bytes([0x00, 1, 0xE0]), 50)  # a long reference cut short


def test_a_compressed_pcd_with_a_corrupt_stream_is_a_format_error(tmp_path):
    path = tmp_path / "c.pcd"
    open3d_write(path, cloud(500, 4), write_ascii=False, compressed=True)
    data = bytearray(path.read_bytes())
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n") + 8
    data[start] = 0x20  # the first run: a back-reference, before the output's start
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match=r"c\.pcd"):
        read_points(path)


# -- writers --------------------------------------------------------------------------------------
@pytest.mark.parametrize("columns", [3, 4])
def test_written_pcd_is_open3ds_file_byte_for_byte(tmp_path, columns):
    pts = cloud(300, columns, seed=1)
    write_points(tmp_path / "ours.pcd", pts)
    open3d_write(tmp_path / "o3d.pcd", pts, write_ascii=False)
    assert (tmp_path / "ours.pcd").read_bytes() == (tmp_path / "o3d.pcd").read_bytes()


@pytest.mark.parametrize("suffix", [".pcd", ".ply"])
@pytest.mark.parametrize("columns", [3, 4, 5, 7])
def test_open3d_reads_the_written_files_to_the_same_arrays(tmp_path, suffix, columns):
    pts = cloud(300, columns, seed=columns)
    write_points(tmp_path / f"w{suffix}", pts)
    np.testing.assert_array_equal(
        open3d_read(tmp_path / f"w{suffix}"), read_points(tmp_path / f"w{suffix}")
    )
    if columns <= 5:  # intensity, ring: already in sorted order
        np.testing.assert_array_equal(read_points(tmp_path / f"w{suffix}"), pts)


def test_structured_readers_return_the_header_and_named_fields(tmp_path):
    path = tmp_path / "s.ply"
    path.write_bytes(ply_bytes(PLY_PROPS, PLY_ROWS, "binary_big_endian"))
    rec, header = read_ply_vertices(path)
    assert header.format == "binary_big_endian" and rec.dtype.names == tuple(
        p for p, _ in PLY_PROPS
    )
    assert rec["label"].tolist() == [-2, 7] and rec["x"].tolist() == [1.5, 4.0]


# -- no Open3D needed -----------------------------------------------------------------------------
def test_pcd_and_ply_need_no_open3d_and_icp_names_the_extra(tmp_path, monkeypatch):
    pts = cloud(100, 4)
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d -> ImportError
    for suffix in (".pcd", ".ply"):
        write_points(tmp_path / f"a{suffix}", pts)
        np.testing.assert_array_equal(read_points(tmp_path / f"a{suffix}"), pts)
    from sparsetools.ops.registration import icp_pose

    with pytest.raises(DependencyError, match=r"sparsetools\[open3d\]"):
        icp_pose(pts[:, :3], pts[:, :3])


def test_reading_a_pcd_loads_neither_open3d_nor_numba_unless_compressed(tmp_path):
    write_points(tmp_path / "a.pcd", cloud(50, 4))
    open3d_write(tmp_path / "c.pcd", cloud(50, 4), write_ascii=False, compressed=True)
    code = (
        "import sys; from sparsetools.io.pointcloud import read_points\n"
        f"read_points({str(tmp_path / 'a.pcd')!r}); read_points({str(tmp_path / 'a.pcd')!r})\n"
        "print('open3d' in sys.modules, 'numba' in sys.modules)\n"
        f"read_points({str(tmp_path / 'c.pcd')!r})\n"
        "print('open3d' in sys.modules, 'numba' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False", "False", "True"]


def test_ascii_packed_colours_and_name_collisions(tmp_path):
    # PCL writes a U-typed rgb as an integer in ascii files: unpacked to r, g, b as in binary
    path = tmp_path / "c.pcd"
    path.write_bytes(pcd_bytes([*XYZ, ("rgb", "U", 4, 1)], [(1, 2, 3, 0x00FF8040)], "ascii"))
    assert read_points(path)[0].tolist() == [1, 2, 3, 255, 128, 64]
    np.testing.assert_array_equal(read_points(path), open3d_read(path))
    # a field named as Open3D names a group of others: which column is which is ambiguous
    fields = [*XYZ, ("normals", "F", 4, 1), ("normal_x", "F", 4, 1), ("normal_y", "F", 4, 1),
              ("normal_z", "F", 4, 1)]  # fmt: skip
    path.write_bytes(pcd_bytes(fields, [(1, 2, 3, 4, 0, 0, 1)]))
    with pytest.raises(FormatError, match="'normals' collides"):
        read_points(path)


def test_a_negative_uncompressed_size_is_refused():
    with pytest.raises(FormatError, match="negative"):
        lzf_decompress(b"\x00a", -1)
