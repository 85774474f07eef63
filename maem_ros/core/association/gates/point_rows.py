"""How the epipolar gate's kernels read one camera's points (:class:`PointRows`: in place, in
runs, with block ranges) and the fundamental matrices of a rig's camera pairs
(:class:`PairMatrices`), and the fixed block order every backend walks."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from maem_ros.core.association.gates.epipolar_constants import BLOCK, ORDER_SEED


@lru_cache(maxsize=32)
def block_order(n: int) -> np.ndarray:
    """(B,2) int64 [start, end) point blocks of ``range(n)`` in the fixed shuffled order."""
    starts = np.arange(0, n, BLOCK, dtype=np.int64)
    blocks = np.stack([starts, np.minimum(starts + BLOCK, n)], axis=1)
    blocks = blocks[np.random.default_rng(ORDER_SEED).permutation(len(blocks))]
    blocks.setflags(write=False)
    return blocks


@lru_cache(maxsize=32)
def block_indices(n: int) -> tuple[np.ndarray, ...]:
    """Point indices of each block of :func:`block_order` (numpy reference path)."""
    return tuple(np.arange(s, e) for s, e in block_order(n))


@dataclass(frozen=True)
class PointRows:
    """One camera's points as the kernel reads them: point k of detection i is
    ``(flat[rows[i] + 2p], flat[rows[i] + 2p + 1])`` rectified px (NaN = missing), p = k when
    ``run`` is 0 (contiguous), else ``(k // run) * period + k % run`` (runs of ``run``
    consecutive points, one every ``period``: a screening subset read in place).

    flat: 1D C-contiguous float32/float64 (may span other message fields between rows, never
    read); rows (N,) int64 element offsets; n points per detection; ranges: None or, for
    points read contiguously (run 0), (N, blocks, 2) float32 each detection's (min, max)
    coordinate over each of its BLOCK-point blocks in their natural order, (inf, -inf) where
    one is NaN (made by screening.screen_copies; the kernel's error bound trusts them).
    """

    flat: np.ndarray
    rows: np.ndarray
    n: int
    run: int = 0
    period: int = 0
    ranges: np.ndarray | None = None

    @property
    def count(self) -> int:
        return int(self.rows.size)

    def positions(self, k: np.ndarray) -> np.ndarray:
        """Point indices k (0 <= k < n) -> their positions p in a detection's row."""
        return k if not self.run else (k // self.run) * self.period + k % self.run

    def contiguous(self) -> PointRows:
        """The same points, each detection's n points contiguous (a copy when read in runs)."""
        return self if not self.run else point_rows(self._gather(self.rows))

    def points(self, i: int) -> np.ndarray:
        """(n,2) copy of detection i's points."""
        return self._gather(self.rows[i : i + 1])[0]

    def _gather(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),n,2) copy of the points of the detections at element offsets rows."""
        at = rows[:, None] + 2 * self.positions(np.arange(self.n))[None, :]
        return np.stack([self.flat[at], self.flat[at + 1]], axis=-1)


def point_rows(x: np.ndarray | PointRows, ranges: np.ndarray | None = None) -> PointRows:
    """(N,n,2) points -> :class:`PointRows`, zero-copy when each detection's (n,2) block is
    contiguous and aligned (a contiguous array, or a field view of a PointCloud2 with one
    detection per point); otherwise one contiguous float64 copy. ranges: the block ranges
    of x's float32 points made by screening.screen_copies (PointRows.ranges), or None."""
    if isinstance(x, PointRows):
        return x
    x = np.asarray(x)
    if x.ndim != 3 or x.shape[2] != 2:
        raise ValueError(f"epipolar points: expected (N,n,2), got {x.shape}")
    N, n = int(x.shape[0]), int(x.shape[1])
    if ranges is not None:
        if ranges.shape != (N, -(-n // BLOCK), 2) or x.dtype != np.float32:
            raise ValueError(
                f"epipolar points: block ranges {ranges.shape} do not describe {x.dtype} points {x.shape}"
            )
        rows = point_rows(x)  # dataclasses.replace took ~5 us a call, 48 a large-load set
        return PointRows(rows.flat, rows.rows, rows.n, rows.run, rows.period, ranges)
    if x.dtype not in (np.float32, np.float64) or not x.dtype.isnative:
        x = x.astype(np.float64)
    if N and n and x.flags.c_contiguous and x.flags.aligned:
        # the common case as a plain view (as_strided and ctypes cost ~10 us a call)
        flat = x.reshape(-1).view()
        flat.flags.writeable = False
        return PointRows(flat, np.arange(N, dtype=np.int64) * (2 * n), n)
    item = x.dtype.itemsize
    inner_ok = n <= 1 or x.strides[1] == 2 * item
    if (
        N
        and n
        and not (
            inner_ok
            and x.strides[2] == item
            and x.strides[0] % item == 0
            and x.strides[0] >= 0
            and x.ctypes.data % item == 0
        )
    ):
        x = np.ascontiguousarray(x)
    if N == 0 or n == 0:
        return PointRows(np.zeros(max(2 * n, 1), dtype=x.dtype), np.zeros(N, dtype=np.int64), n)
    step = x.strides[0] // item if N > 1 else 2 * n
    span = (N - 1) * step + 2 * n
    flat = np.lib.stride_tricks.as_strided(x, shape=(span,), strides=(item,), writeable=False)
    return PointRows(flat, np.arange(N, dtype=np.int64) * step, n)


@dataclass(frozen=True)
class PairMatrices:
    """Fundamental matrices of ordered camera pairs as the kernels take them, prepared once
    (per rig) instead of per call: ``unit[lookup[a * cameras + b]]`` (9,) is F[(a, b)]
    (``x_b^T F x_a = 0``) scaled to unit Frobenius norm (distances do not depend on F's
    scale; the error bounds assume it), row-major; lookup -1 where no F was given."""

    cameras: int
    lookup: np.ndarray
    unit: np.ndarray

    def rows(self, cam_a: np.ndarray, cam_b: np.ndarray) -> np.ndarray:
        """(S,) rows of unit of the camera pairs (cam_a[s], cam_b[s]); ValueError naming the
        first pair without an F."""
        inside = (cam_a < self.cameras) & (cam_b < self.cameras)
        rows = np.full(cam_a.shape, -1, dtype=np.int64)
        rows[inside] = self.lookup[cam_a[inside] * self.cameras + cam_b[inside]]
        if rows.size and rows.min() < 0:
            s = int(np.argmin(rows))
            raise ValueError(
                f"epipolar pairs: no fundamental matrix for camera pair {(int(cam_a[s]), int(cam_b[s]))}"
            )
        return rows


def pair_matrices(F: Mapping[tuple[int, int], np.ndarray] | PairMatrices) -> PairMatrices:
    """F[(a, b)] (3,3) per ordered camera pair -> :class:`PairMatrices` (returned as is when
    it is one already)."""
    if isinstance(F, PairMatrices):
        return F
    keys = list(F)
    if any(min(k) < 0 for k in keys):
        raise ValueError(f"epipolar: camera indices must be >= 0, got {min(keys, key=min)}")
    C = max((max(k) for k in keys), default=-1) + 1
    unit = np.array([np.asarray(F[k], dtype=np.float64).reshape(9) for k in keys]).reshape(-1, 9)
    norm = np.sqrt((unit * unit).sum(axis=1))
    unit = unit / np.where(norm > 0, norm, 1.0)[:, None]
    lookup = np.full(C * C, -1, dtype=np.int64)
    lookup[[a * C + b for a, b in keys]] = np.arange(len(keys))
    return PairMatrices(C, lookup, unit)
