"""Builds the hardening corpus at test time: small valid inputs and bad variants of them.

Nothing here is committed as binary data: every file is written into a pytest ``tmp_path``
by the functions below. :data:`CASES` is the table of (command, bad input) cases that
``test_corpus.py`` runs; each case builds its inputs under ``tmp/in``, names its output
under ``tmp/out`` and says what must happen (a one-line error, a usage error, or the
documented non-error behaviour).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sparsetools.io.atomic import TMP_PREFIX
from sparsetools.io.provenance import RECORD_DIR

# -- geometry of the small valid frame ----------------------------------------------------------

W, H = 64, 32
K = np.array([[40.0, 0.0, W / 2], [0.0, 40.0, H / 2], [0.0, 0.0, 1.0]])
#: KITTI Velodyne -> camera axes (x forward, y left, z up -> x right, y down, z forward).
VELO_TO_CAM = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]])


def fmt_values(a) -> str:
    return " ".join(f"{v:.12e}" for v in np.asarray(a, dtype=np.float64).ravel())


def kitti_calib_text(*, P2=None, R0=None, Tr=None, drop: str | None = None) -> str:
    """A KITTI object calib file; ``drop`` leaves one key out."""
    P = np.hstack([K, np.zeros((3, 1))]) if P2 is None else P2
    rows = {f"P{i}": fmt_values(P) for i in range(4)}
    rows["R0_rect"] = fmt_values(np.eye(3) if R0 is None else R0)
    rows["Tr_velo_to_cam"] = fmt_values(VELO_TO_CAM if Tr is None else Tr)
    if drop is not None:
        rows.pop(drop)
    return "".join(f"{k}: {v}\n" for k, v in rows.items())


def json_calib(**override) -> dict:
    T = np.eye(4)
    T[:3] = VELO_TO_CAM
    d = {"K": K.tolist(), "T_cam_from_sensor": T.tolist(), "width": W, "height": H}
    d.update(override)
    return d


def cloud(n: int = 3000, seed: int = 0) -> np.ndarray:
    """(n, 4) float32 Velodyne points, all in front of the camera and inside the image."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(4.0, 40.0, n)
    y = rng.uniform(-0.6, 0.6, n) * x
    z = rng.uniform(-0.3, 0.3, n) * x
    r = rng.uniform(0.0, 1.0, n)
    return np.stack([x, y, z, r], axis=1).astype(np.float32)


def rgb_image(seed: int = 0, w: int = W, h: int = H) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = np.linspace(30, 220, w, dtype=np.float64)[None, :, None]
    img = base + rng.normal(0, 12, (h, w, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def png_bytes(array: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", array)
    assert ok
    return buf.tobytes()


def jpeg_bytes(array: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".jpg", array)
    assert ok
    return buf.tobytes()


def depth_map(seed: int = 0, w: int = W, h: int = H, density: float = 0.3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.uniform(2.0, 60.0, (h, w)).astype(np.float32)
    d[rng.random((h, w)) > density] = 0
    return d


def depth_png_bytes(depth: np.ndarray) -> bytes:
    return png_bytes(np.clip(np.rint(depth * 256), 0, 65535).astype(np.uint16))


def bomb_png(width: int = 200_000, height: int = 200_000) -> bytes:
    """A valid PNG header declaring a huge image, followed by a tiny compressed stream."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 4096)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def corrupt_png() -> bytes:
    """PNG signature and a valid IHDR, then garbage instead of the image data."""
    good = png_bytes(rgb_image())
    return good[:33] + bytes(range(256)) * 4


def corrupt_jpeg() -> bytes:
    good = jpeg_bytes(rgb_image())
    return good[:2] + b"\x00" * 64 + good[200:260]


def truncated(data: bytes, keep: float = 0.5) -> bytes:
    return data[: max(1, int(len(data) * keep))]


def radar_pcd_bytes(n: int = 20, declared: int | None = None, seed: int = 0) -> bytes:
    from sparsetools.io.nuscenes import RADAR_DTYPE, RADAR_FIELDS, RADAR_SIZES, RADAR_TYPES

    rng = np.random.default_rng(seed)
    rec = np.zeros(n, dtype=RADAR_DTYPE)
    rec["x"] = rng.uniform(5, 40, n)
    rec["y"] = rng.uniform(-5, 5, n)
    rec["dyn_prop"] = 1
    rec["ambig_state"] = 3
    m = n if declared is None else declared
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(RADAR_FIELDS)}\nSIZE {' '.join(map(str, RADAR_SIZES))}\n"
        f"TYPE {' '.join(RADAR_TYPES)}\nCOUNT {' '.join('1' for _ in RADAR_FIELDS)}\n"
        f"WIDTH {m}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {m}\nDATA binary\n"
    )
    return header.encode("ascii") + rec.tobytes()


def npy_bytes(array) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=True)
    return buf.getvalue()


def npy_huge_header(rows: int = 10**13, cols: int = 4) -> bytes:
    """A valid .npy header declaring a huge float32 array, followed by a few bytes of data."""
    small = npy_bytes(np.zeros((10, cols), np.float32))
    head, _, _ = small.partition(b"(10, %d)" % cols)
    rest = small[len(head) + len(b"(10, %d)" % cols) :]
    declared = b"(%d, %d)" % (rows, cols)
    # Keep the header length (padding spaces) so the data offset stays 16-byte aligned.
    pad = len(declared) - len(b"(10, %d)" % cols)
    rest = rest.replace(b" " * pad + b"\n", b"\n", 1)
    return head + declared + rest[: rest.index(b"\n") + 1] + b"\x00" * 64


# -- trees -----------------------------------------------------------------------------------------


def write(path: Path, data: bytes | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(data, str):
        path.write_text(data, encoding="utf-8")
    else:
        path.write_bytes(data)
    return path


def good_frame(root: Path, stem: str = "000000", seed: int = 0) -> dict[str, Path]:
    """One valid frame: velodyne/, calib/, image_2/, depth/ (sparse), gt/ under ``root``.

    Files that exist already are kept (a case may have replaced one by a bad version).
    """
    files = {
        "cloud": (root / "velodyne" / f"{stem}.bin", lambda: cloud(seed=seed).tobytes()),
        "calib": (root / "calib" / f"{stem}.txt", kitti_calib_text),
        "image": (root / "image_2" / f"{stem}.png", lambda: png_bytes(rgb_image(seed))),
        "depth": (root / "depth" / f"{stem}.png", lambda: depth_png_bytes(depth_map(seed))),
        "gt": (
            root / "gt" / f"{stem}.png",
            lambda: depth_png_bytes(depth_map(seed + 7, density=0.9)),
        ),
    }
    out = {}
    for key, (path, make) in files.items():
        if not path.exists() and not path.is_symlink():
            write(path, make())
        out[key] = path
    return out


def replicate(root: Path, n: int) -> dict[str, Path]:
    """``n`` frames: copies of one valid frame under new stems (distinct per-frame seeds)."""
    f = good_frame(root)
    for i in range(1, n):
        stem = f"{i:06d}"
        for key in ("cloud", "image", "depth"):
            src = f[key]
            shutil.copyfile(src, src.with_name(stem + src.suffix))
    return f


def underwater_tree(root: Path, n_seafloor: int = 3, n_water: int = 2) -> tuple[Path, Path]:
    rng = np.random.default_rng(5)
    sea, water = root / "seafloor", root / "water"
    for i in range(n_seafloor):
        write(sea / f"{i:06d}.png", png_bytes(rng.integers(40, 200, (H, W, 3), dtype=np.uint8)))
    for i in range(n_water):
        write(water / f"{i:06d}.png", png_bytes(rng.integers(0, 30, (H, W, 3), dtype=np.uint8)))
    return sea, water


def tree_digest(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of content (or the link target for symbolic links).

    Files of the folder's records (``.sparsetools/``) are digested without what differs
    between two folders made alike: the folder's own path and the modification times of the
    files inside it (outputs, and inputs that an earlier stage wrote there), see
    :func:`record_text`.
    """
    out = {}
    if not root.exists():
        return out
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if p.is_symlink():
            out[rel] = "link:" + os.readlink(p)
        elif p.is_file():
            data = p.read_bytes()
            if RECORD_DIR in p.relative_to(root).parts:
                data = record_text(data, root).encode()
            out[rel] = hashlib.sha256(data).hexdigest()
        elif p.is_dir():
            out[rel] = "dir"
    return out


def record_text(data: bytes, root: Path) -> str:
    """A record file (JSON or JSON lines) with ``root`` written ``<OUT>`` and the mtimes of
    the files under it left out (the times of ``[path, size, mtime, sha256]`` input
    identities under ``root`` and of every ``[size, mtime, digest]`` output identity);
    sizes and hashes stay, so a truncated or different output still shows."""
    text = data.decode("utf-8", errors="replace")
    for prefix in {str(root.resolve()), os.path.abspath(root)}:
        text = text.replace(prefix, "<OUT>")
    lines = []
    for line in text.splitlines():
        try:
            item = json.loads(line)
        except ValueError:
            lines.append(line)
            continue
        if isinstance(item, dict):
            for ident in (item.get("output_ids") or {}).values():
                if isinstance(ident, list) and len(ident) == 3:
                    ident[1] = None
            for ident in item.get("inputs") or ():
                if (
                    isinstance(ident, list)
                    and len(ident) == 4
                    and str(ident[0]).startswith("<OUT>")
                ):
                    ident[2] = None
        lines.append(json.dumps(item, sort_keys=True))
    return "\n".join(lines)


def new_files(before: dict[str, str], root: Path) -> list[str]:
    """Files (not folders) under ``root`` that are new or changed since ``before``."""
    after = tree_digest(root)
    return sorted(k for k, v in after.items() if v != "dir" and before.get(k) != v)


def temp_files(root: Path) -> list[str]:
    if not root.exists():
        return []
    return sorted(str(p) for p in root.rglob(".tmp-sparsetools-*"))


# -- interrupting a run ----------------------------------------------------------------------


class InterruptAt:
    """``os.replace`` that raises KeyboardInterrupt at its ``n``-th call (1-based).

    Only renames of the command's own outputs count: numba writes its on-disk cache with
    ``os.replace`` too, on the first run in a fresh checkout only, which would shift the count.
    """

    def __init__(self, n: int):
        self.n = n
        self.calls = 0
        self.real = os.replace

    def __call__(self, src, dst, *a, **kw):
        if TMP_PREFIX in os.path.basename(os.fspath(src)):
            self.calls += 1
            if self.calls == self.n:
                raise KeyboardInterrupt
        return self.real(src, dst, *a, **kw)


# -- permission bits that bind root too -------------------------------------------------------

#: Runs ``sparsetools ARGV[1:]`` in a process that first gives up the capabilities that let
#: root ignore permission bits (CAP_DAC_OVERRIDE 1, CAP_DAC_READ_SEARCH 2: dropping one's own
#: capabilities needs no privilege). It stays uid 0 in this process (no exec, which would
#: give root every capability back), so it still reads root's 0700 temporary folders as their
#: owner, but a ``chmod 555`` folder is read-only for it, as for any user.
_WITHOUT_DAC_OVERRIDE = """
import ctypes, sys
libc = ctypes.CDLL(None, use_errno=True)
class Header(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]
class Data(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                ("inheritable", ctypes.c_uint32)]
header, data = Header(0x20080522, 0), (Data * 2)()
if libc.capget(ctypes.byref(header), data) != 0:
    sys.exit("capget failed")
keep = ~((1 << 1) | (1 << 2)) & 0xFFFFFFFF
for field in ("effective", "permitted", "inheritable"):
    setattr(data[0], field, getattr(data[0], field) & keep)
if libc.capset(ctypes.byref(header), data) != 0:
    sys.exit("capset failed")
from sparsetools.cli.main import main
main(sys.argv[1:])
"""


@dataclass
class ProcessResult:
    """What :func:`invoke_bound_by_permissions` returns: the fields of click's ``Result``
    that the suite reads."""

    exit_code: int
    stdout: str
    stderr: str
    exception: BaseException | None = None

    @property
    def output(self) -> str:
        return self.stdout + self.stderr


def invoke_bound_by_permissions(args) -> ProcessResult:
    """``sparsetools ARGS`` as a process to which permission bits apply, even when the suite
    runs as root (as CI does): root's run gives up CAP_DAC_OVERRIDE and CAP_DAC_READ_SEARCH
    first (see :data:`_WITHOUT_DAC_OVERRIDE`)."""
    proc = subprocess.run(
        [sys.executable, "-c", _WITHOUT_DAC_OVERRIDE, *map(str, args)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert "capset failed" not in proc.stderr and "capget failed" not in proc.stderr, proc.stderr
    return ProcessResult(proc.returncode, proc.stdout, proc.stderr)


# -- the case table ------------------------------------------------------------------------------


@dataclass
class Setup:
    """What a case's builder returns."""

    args: list
    out: Path | None = None  # output file or folder to watch (default: tmp/out)
    allowed_outputs: tuple[str, ...] = ()  # output files that may appear (documented)
    check: Callable[[Path, object], None] | None = None  # extra assertion (tmp, result)


@dataclass
class Case:
    id: str
    build: Callable[[Path], Setup]
    expect: str = "error"  # "error" (exit 1), "usage" (exit 2) or "ok" (documented, exit 0)
    match: str = ""  # substring of the error line (case-insensitive)
    #: False: the case needs permission bits (a read-only folder); run by root, it runs in a
    #: process without the capabilities that bypass them (:func:`invoke_bound_by_permissions`).
    #: True: run only as root.
    root_only: bool | None = None
    xfail: str = ""
    marks: list = field(default_factory=list)
