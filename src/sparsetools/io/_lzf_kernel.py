"""The compiled LZF decoding loop of :mod:`.lzf` (imported only when a compressed PCD is read,
so that numba loads only then)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lzf_decode(src, dst):  # pragma: no cover - jitted
    """Decode ``src`` (uint8) into ``dst`` (uint8); the bytes written, or -1 when corrupt."""
    n_in = src.size
    n_out = dst.size
    ip = 0
    op = 0
    while ip < n_in:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n_in or op + length > n_out:
                return -1
            for k in range(length):
                dst[op + k] = src[ip + k]
            ip += length
            op += length
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= n_in:
                    return -1
                length += np.int64(src[ip])
                ip += 1
            if ip >= n_in:
                return -1
            ref = op - ((ctrl & 31) << 8) - np.int64(src[ip]) - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > n_out:
                return -1
            for k in range(length):  # byte by byte: the source may overlap the output
                dst[op + k] = dst[ref + k]
            op += length
    return op
