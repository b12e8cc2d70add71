"""``.npy`` arrays from untrusted files: no pickles, and no allocation a file cannot back.

``np.load`` trusts the header: a file of a few bytes that declares a shape of 10^13 rows
makes it allocate terabytes (``MemoryError``) before noticing that the data is missing.
:func:`load_npy` checks the declared size against the bytes present first.
"""

from __future__ import annotations

import io
import math
import warnings

import numpy as np

from ..errors import FormatError

__all__ = ["load_npy"]


def _header(npy_format, fh):
    version = npy_format.read_magic(fh)
    if version == (1, 0):
        shape, _fortran, dtype = npy_format.read_array_header_1_0(fh)
    elif version in ((2, 0), (3, 0)):
        shape, _fortran, dtype = npy_format.read_array_header_2_0(fh)
    else:
        raise ValueError(f"unsupported .npy format version {version}")
    return shape, dtype


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
        Not a ``.npy`` file, an unsupported version, an object (pickled) array, or a header
        whose shape and dtype do not match the number of data bytes (truncated or corrupt).
    """
    from numpy.lib import format as npy_format

    fh = io.BytesIO(data)
    try:
        with warnings.catch_warnings():  # "created on Python 2" and the like: not our output
            warnings.simplefilter("ignore")
            shape, dtype = _header(npy_format, fh)
    except Exception as exc:  # numpy parses the header with ast/tokenize: many error types
        raise FormatError(f"{source}: {invalid} ({' '.join(str(exc).split())})") from exc
    if dtype.hasobject:
        raise FormatError(f"{source}: {invalid} (object arrays hold pickles, which are refused)")
    need = math.prod(int(s) for s in shape) * dtype.itemsize
    have = len(data) - fh.tell()
    if need != have:
        raise FormatError(
            f"{source}: {invalid} (the header declares {dtype} {tuple(shape)}, {need} bytes; "
            f"the file holds {have}: truncated or corrupt)"
        )
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, EOFError, OSError) as exc:  # pragma: no cover - checked above
        raise FormatError(f"{source}: {invalid} ({' '.join(str(exc).split())})") from exc
