"""``.npy`` arrays from untrusted files: no pickles, no allocation a file cannot back, and the
pixel limit of every image input.

``np.load`` trusts the header: a file of a few bytes that declares a shape of 10^13 rows
makes it allocate terabytes (``MemoryError``) before noticing that the data is missing.
:func:`load_npy` checks the declared size against the bytes present first, and the declared
shape against the pixel limit PNG inputs have (:func:`sparsetools.io.image.check_pixel_count`,
``SPARSETOOLS_MAX_IMAGE_PIXELS``): an (H, W, ...) array counts H x (W x ...) elements.
:func:`check_npy_file` reads only a file's header, so a caller refuses a huge array before
reading it.
"""

from __future__ import annotations

import io
import math
import warnings

import numpy as np

from ..errors import FormatError

__all__ = ["MAX_MAP_FILE_BYTES", "check_npy_file", "check_npy_shape", "load_npy", "read_map_bytes"]

#: Largest depth-like map file read (bytes): a map at the default pixel limit as an
#: uncompressed float32 ``.npy`` is 256 MiB; float64 with a few channels stays well below.
MAX_MAP_FILE_BYTES = 4 << 30

#: Largest .npy header read (bytes): numpy's own limit for untrusted headers.
_MAX_HEADER = 10000


def _header(npy_format, fh):
    version = npy_format.read_magic(fh)
    if version == (1, 0):
        return npy_format.read_array_header_1_0(fh)
    if version in ((2, 0), (3, 0)):
        return npy_format.read_array_header_2_0(fh)
    raise ValueError(f"unsupported .npy format version {version}")


#: Parsed headers by their exact bytes (magic to the end of the header dict): the frames of a
#: dataset share one header, and numpy parses it with ``ast`` (~80 us each time).
_parsed: dict[bytes, tuple] = {}
_PARSED_MAX = 256


def _header_bytes(fh) -> bytes | None:
    """The bytes from ``fh``'s position to the end of its header (position unchanged);
    None when they are not a well-formed prefix (numpy's parse then says why)."""
    start = fh.tell()
    head = fh.read(12)
    fh.seek(start)
    if len(head) < 10 or head[:6] != b"\x93NUMPY":
        return None
    if head[6] == 1:
        end = 10 + int.from_bytes(head[8:10], "little")
    elif head[6] in (2, 3) and len(head) == 12:
        end = 12 + int.from_bytes(head[8:12], "little")
    else:
        return None
    if end > _MAX_HEADER + 16:
        return None
    data = fh.read(end)
    fh.seek(start)
    return data if len(data) == end else None


def check_npy_shape(shape, source: str) -> None:
    """Refuse a declared shape above the pixel limit (H x the product of the other
    dimensions; a 1-D array counts its length)."""
    from .image import check_pixel_count

    dims = [int(d) for d in shape]
    height = dims[0] if dims else 1
    width = math.prod(dims[1:]) if len(dims) > 1 else 1
    check_pixel_count(width, height, f"{source}: declared size")


def _read_header(fh, source: str, invalid: str):
    """(shape, fortran_order, dtype) of the header at ``fh``'s position; ``fh`` is left at
    the first data byte. Object (pickled) arrays are refused."""
    from numpy.lib import format as npy_format

    key = _header_bytes(fh)
    parsed = _parsed.get(key) if key is not None else None
    if parsed is None:
        start = fh.tell()
        try:
            with warnings.catch_warnings():  # "created on Python 2" and the like: not ours
                warnings.simplefilter("ignore")
                parsed = _header(npy_format, fh)
        except Exception as exc:  # numpy parses the header with ast/tokenize: many error types
            raise FormatError(f"{source}: {invalid} ({' '.join(str(exc).split())})") from exc
        if key is not None and fh.tell() - start == len(key):
            if len(_parsed) >= _PARSED_MAX:
                _parsed.clear()
            _parsed[key] = parsed
    else:
        fh.seek(fh.tell() + len(key))
    dtype = parsed[2]
    if dtype.hasobject:
        raise FormatError(f"{source}: {invalid} (object arrays hold pickles, which are refused)")
    return parsed


def _check_size(shape, dtype, have: int, source: str, invalid: str) -> None:
    need = math.prod(int(s) for s in shape) * dtype.itemsize
    if need != have:
        raise FormatError(
            f"{source}: {invalid} (the header declares {dtype} {tuple(shape)}, {need} bytes; "
            f"the file holds {have}: truncated or corrupt)"
        )
    check_npy_shape(shape, source)


def check_npy_file(path, *, invalid: str = "not a valid .npy array") -> tuple:
    """Read only the header of a ``.npy`` file and check it (no pickle, the pixel limit, the
    declared size equal to the data present) before the file is read; return its shape.

    Raises
    ------
    FormatError
        Unreadable, not a regular file, or a header :func:`load_npy` would refuse.
    """
    import os
    import stat

    source = str(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # a FIFO must not block
        with os.fdopen(fd, "rb") as fh:
            st = os.fstat(fh.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise FormatError(f"{source}: not a regular file (a device or a pipe?)")
            head = io.BytesIO(fh.read(_MAX_HEADER + 16))
    except OSError as exc:
        raise FormatError(f"{source}: cannot read ({exc.strerror or exc})") from exc
    shape, _fortran, dtype = _read_header(head, source, invalid)
    _check_size(shape, dtype, st.st_size - head.tell(), source, invalid)
    return tuple(int(s) for s in shape)


def load_npy(data: bytes, *, source: str, invalid: str = "not a valid .npy array") -> np.ndarray:
    """Decode the bytes of a ``.npy`` file.

    Parameters
    ----------
    data : bytes
        The whole file.
    source : str
        File name for messages.
    invalid : str
        Wording of the error (``"<source>: <invalid> (<detail>)"``).

    Returns
    -------
    ndarray
        As stored (any numeric or string dtype; object arrays are refused).

    Raises
    ------
    FormatError
        Not a ``.npy`` file, an unsupported version, an object (pickled) array, a shape above
        the pixel limit, or a header whose shape and dtype do not match the number of data
        bytes (truncated or corrupt).
    """
    fh = io.BytesIO(data)
    shape, fortran, dtype = _read_header(fh, source, invalid)
    offset = fh.tell()
    _check_size(shape, dtype, len(data) - offset, source, invalid)
    # The header is parsed and checked: the data are the rest, as np.load would read them
    # (a copy: writable, and not holding the file's bytes).
    flat = np.frombuffer(data, dtype=dtype, count=math.prod(int(d) for d in shape), offset=offset)
    return flat.reshape(shape, order="F" if fortran else "C").copy(order="K")


def read_map_bytes(path, *, what: str) -> bytes:
    """The bytes of a depth-like map file (PNG or ``.npy``): a regular file (a link to
    ``/dev/zero`` would be read forever, a FIFO would block) of at most
    :data:`MAX_MAP_FILE_BYTES`; a ``.npy`` has its header checked first
    (:func:`check_npy_file`), so an array above the pixel limit is refused before it is read.

    Raises
    ------
    FormatError
        Missing, unreadable, not a regular file, too large, or a refused ``.npy`` header.
    """
    from pathlib import Path

    from .sidecar import read_regular_file

    if Path(path).suffix.lower() == ".npy":
        check_npy_file(path, invalid="not a readable .npy array")
    try:
        return read_regular_file(path, what=f"{what} file", max_bytes=MAX_MAP_FILE_BYTES)
    except FileNotFoundError as exc:
        raise FormatError(f"{path}: cannot read {what} (no such file)") from exc
