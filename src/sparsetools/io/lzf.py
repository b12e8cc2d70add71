"""LZF decompression (Marc Lehmann's liblzf format), as used by PCD ``binary_compressed``.

The stream is a sequence of runs, each opened by one control byte ``c``:

- ``c < 32``: a literal run, the next ``c + 1`` bytes are copied as they are;
- otherwise a back-reference: length ``(c >> 5) + 2`` (when ``c >> 5 == 7``, the next byte
  is added to the length), distance ``((c & 31) << 8) + next byte + 1`` back from the
  current output position; the copy may overlap what it writes (a run of one byte repeats).

The decoder is a compiled loop (numba, cached on disk) that refuses, instead of reading or
writing out of bounds, every stream that points before the output's start, runs past its own
end or would overflow the declared output size.
"""

from __future__ import annotations

import numpy as np

from ..errors import FormatError

__all__ = ["lzf_decompress"]


def _kernel():
    from ._lzf_kernel import lzf_decode

    return lzf_decode


def lzf_decompress(data: bytes | np.ndarray, size: int, *, source: str = "LZF data") -> bytes:
    """Decompress an LZF stream that must expand to exactly ``size`` bytes.

    Parameters
    ----------
    data : bytes or (M,) uint8
        The compressed stream (nothing before or after it).
    size : int
        The declared uncompressed size, in bytes (>= 0).
    source : str
        Names the data in errors (a file path).

    Returns
    -------
    bytes
        ``size`` bytes.

    Raises
    ------
    FormatError
        The stream is corrupt (a reference before the start, a run past the end of the stream
        or of the output) or expands to a size other than ``size``.
    """
    src = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
    if size < 0:
        raise FormatError(f"{source}: negative uncompressed size {size}")
    dst = np.empty(size, dtype=np.uint8)
    if src.size == 0:
        written = 0
    else:
        written = int(_kernel()(src, dst))
    if written == -1:
        raise FormatError(f"{source}: corrupt LZF stream (a run points outside the data)")
    if written != size:
        raise FormatError(
            f"{source}: the LZF stream expands to {written} bytes, the header declares {size}"
        )
    return dst.tobytes()
