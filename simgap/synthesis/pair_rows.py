"""(cell, input) pairs as rows: flat pair ids, rows packed as bits, blocks of rows.

The games keep a set of pairs as (N, ceil(M/8)) uint8 rows (np.packbits order along the M
inputs) between their stages, and as (N*M,) bool indexed by the flat pair id c * M + u in the
worklists. Passes over all pairs go in blocks of about 2^18 pairs (:func:`_block_size`).
"""

from __future__ import annotations

import numpy as np

from .abstraction import Abstraction


def _block_size(ab: Abstraction) -> int:
    # about 2^18 (cell, input) pairs per block keeps the temporaries small (cache friendly)
    return max(1, (1 << 18) // max(1, ab.n_inputs))


def _unpack(packed: np.ndarray, M: int) -> np.ndarray:
    """(N, ceil(M/8)) packed bits -> (N*M,) bool, pair id c * M + u."""
    return unpack_rows(packed, M).reshape(-1)


def unpack_rows(packed: np.ndarray, M: int) -> np.ndarray:
    """(N, ceil(M/8)) bits (np.packbits order) -> (N, M) bool; column by column for few inputs
    (np.unpackbits along a short axis is several times slower)."""
    if M > 16:
        return np.unpackbits(packed, axis=1, count=M).view(bool)
    out = np.empty((packed.shape[0], M), dtype=bool)
    for u in range(M):
        np.not_equal(packed[:, u >> 3] & np.uint8(0x80 >> (u & 7)), 0, out=out[:, u])
    return out


def pack_rows(rows: np.ndarray) -> np.ndarray:
    """(N, M) bool -> (N, ceil(M/8)) uint8, as np.packbits(rows, axis=1)."""
    N, M = rows.shape
    if M > 16:
        return np.packbits(rows, axis=1)
    out = np.zeros((N, (M + 7) // 8), dtype=np.uint8)
    for u in range(M):
        out[:, u >> 3] |= rows[:, u].view(np.uint8) << np.uint8(7 - (u & 7))
    return out
