"""The q4 vertex decoder's numba kernel: :func:`maem_ros.wire.detections.decode_q4`'s fast path
for float32 output. A full mesh (442k codes per message) is decoded for every processed frame
set; numpy needs four passes over it (cast, scale, origin, missing marker), this kernel one
vectorised pass per detection.

Bit-identical to the numpy path: code / 16 and the integer origin are exact in float32.
"""

from __future__ import annotations

import numpy as np

from maem_ros.core.jit import have_numba, jit

#: the largest code marks a missing vertex (wire.detections.Q4_MISSING)
_MISSING = 65535
_STEP = np.float32(1.0 / 16.0)
_NAN = np.float32(np.nan)


@jit
def _decode_row(code: np.ndarray, u0: np.float32, v0: np.float32, out: np.ndarray) -> None:
    """One detection: code (2K,) uint16 (u, v) pairs -> out (2K,) float32 px, code / 16 plus
    the origin (u0, v0) px, NaN where the code is the missing marker. A select, not a branch,
    and contiguous rows: the loop vectorises."""
    for k in range(code.shape[0]):
        c = code[k]
        value = np.float32(c) * _STEP + (u0 if (k & 1) == 0 else v0)
        out[k] = _NAN if c == _MISSING else value


def decode_pairs(code: np.ndarray, origin: np.ndarray) -> np.ndarray | None:
    """code (N, 2K) uint16 with contiguous rows (a message field: rows a point_step apart),
    origin (N, 2) px -> the decoded (N, 2K) float32 array; None without numba or for other
    layouts (the caller's numpy path)."""
    if (
        not have_numba()
        or code.ndim != 2
        or code.dtype != np.uint16
        or (code.shape[1] > 1 and code.strides[1] != code.itemsize)
    ):
        return None
    out = np.empty(code.shape, np.float32)
    start = np.asarray(origin, np.float32)
    for i in range(len(code)):  # per detection: each call runs over its 2K codes
        _decode_row(code[i], start[i, 0], start[i, 1], out[i])
    return out


def warmup() -> None:
    """Compile (or load) the kernel for the rows the decoder sees: writable, and read-only
    (the fields of a received message)."""
    origin = np.zeros((2, 2), np.float32)
    record = np.zeros(2, np.dtype([("a", np.float32, 3), ("c", np.uint16, 8)]))
    decode_pairs(record["c"], origin)
    decode_pairs(np.frombuffer(record.tobytes(), record.dtype)["c"], origin)
