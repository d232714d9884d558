"""Compiled LZF decompression for :func:`nkf_model.io.pcd.lzf_decompress` (PCD binary_compressed).

The same loop as the Python version there, over uint8 arrays; returns the number of bytes written,
or a negative code for a corrupt stream (-1 a literal run past the end, -2 a reference past the
end of the input, -3 a reference out of range). Byte by byte copies keep overlapping references
right (they repeat the last ``distance`` bytes).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(nogil=True, cache=True)
def lzf_into(src: np.ndarray, out: np.ndarray) -> int:
    ip, op = 0, 0
    n, size = src.shape[0], out.shape[0]
    while ip < n:
        ctrl = np.int64(src[ip])
        ip += 1
        if ctrl < 32:
            length = ctrl + 1
            if ip + length > n or op + length > size:
                return -1
            out[op : op + length] = src[ip : ip + length]
            ip += length
            op += length
        else:
            length = ctrl >> 5
            if length == 7:
                if ip >= n:
                    return -2
                length += np.int64(src[ip])
                ip += 1
            if ip >= n:
                return -2
            ref = op - ((ctrl & 0x1F) << 8) - np.int64(src[ip]) - 1
            ip += 1
            length += 2
            if ref < 0 or op + length > size:
                return -3
            for k in range(length):
                out[op + k] = out[ref + k]
            op += length
    return op
