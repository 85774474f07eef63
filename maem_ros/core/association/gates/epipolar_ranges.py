"""The coordinate range of a block of float32 points, for the epipolar kernel's bounds
(epipolar_blocks, epipolar_kernel): min and max over the float bits as ordered int32 keys (so the
reductions vectorise), cached per detection and block (the prepared frame's block ranges)."""

from __future__ import annotations

import numpy as np

from maem_ros.core.association.gates.epipolar_constants import KEY_NEG_INF, KEY_POS_INF
from maem_ros.core.association.gates.epipolar_jit import inline, plain, wide_vectors


@inline
def block_range(x, ranges, d, r):
    """(min, max) of all coordinates of detection d's block r of float32 points x (2m,),
    cached in ranges[d, r] (the prepared frame's, screening.screen_copies, when given); (inf, -inf) if
    one is NaN or inf. The cached case inlined (the kernel asks ~3 times a pair and block),
    the scan a call."""
    if ranges[d, r, 0] == ranges[d, r, 0]:
        return ranges[d, r, 0], ranges[d, r, 1]
    return scan_range(x, ranges, d, r)


@plain
def scan_range(x, ranges, d, r):
    """block_range of a block not cached yet: scanned, then cached."""
    wide_vectors()
    lo, hi = key_range(x.view(np.int32))
    ranges[d, r, 0], ranges[d, r, 1] = key_values(lo, hi)
    return ranges[d, r, 0], ranges[d, r, 1]


_LOW31 = np.int32(0x7FFFFFFF)


@inline
def key_range(bits):
    """(min, max) ordered int32 keys of float32 values (their int32 bits): ordered keys of
    the float bits, so the min/max reductions vectorise."""
    lo = np.int32(2147483647)
    hi = np.int32(-2147483648)
    for k in range(bits.shape[0]):
        b = bits[k]
        # int32 throughout and selects, not min(): the loop vectorises
        key = np.int32(b ^ (np.int32(b >> np.int32(31)) & _LOW31))
        lo = key if key < lo else lo
        hi = key if key > hi else hi
    return lo, hi


@inline
def key_values(lo, hi):
    """key_range's keys as (min, max) float values; (inf, -inf) if a value is NaN or inf."""
    if lo <= KEY_NEG_INF or hi >= KEY_POS_INF:
        return np.inf, -np.inf
    keys = np.empty(2, dtype=np.int32)
    keys[0] = lo ^ ((lo >> 31) & _LOW31)
    keys[1] = hi ^ ((hi >> 31) & _LOW31)
    vals = keys.view(np.float32)
    return np.float64(vals[0]), np.float64(vals[1])
