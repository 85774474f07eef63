"""Epipolar gate kernels: mean point-to-epipolar-line distance between corresponding points.

For a camera pair (a, b) with ``x_b^T F x_a = 0`` (rectified pinhole px) and two detections
whose point k is the same body spot (mesh vertex or keypoint), the per-point distance is

    forward:    d_k = |x_b^T F x_a| / ||(F x_a)_12||                 (x_b to the line of x_a in b)
    symmetric:  d_k = 0.5 |x_b^T F x_a| (1/||(F x_a)_12|| + 1/||(F^T x_b)_12||)

and a pair is rejected when ``sum_k d_k >= tau * n`` (i.e. the mean >= tau, px).

Exact early exit: d_k >= 0, so once a partial sum (points walked in one fixed shuffled order,
in chunks) reaches ``tau * n`` the full sum does too and the pair is rejected; accepted pairs
are always summed completely. Floating-point addition of non-negative numbers is monotone,
so with the same chunking the decision is bit-identical to the full sum.

Two backends with the same order and chunking: a numba kernel (fast path; SIMD over
contiguous 64-point blocks) and a vectorised numpy reference. A point at the epipole has an
undefined line; its distance is inf, which rejects the pair.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

#: points per contiguous block (SIMD-friendly); blocks are visited in a fixed shuffled order
BLOCK = 64
#: blocks per early-exit check (512 points)
CHUNK_BLOCKS = 8
#: seed of the fixed block order (any fixed value; part of the definition of "the order")
ORDER_SEED = 20240611

try:  # numba is optional: the numpy reference gives the same decisions, only slower
    import numba as _numba
except ImportError:  # pragma: no cover - exercised only without numba
    _numba = None

BACKENDS = ("auto", "numba", "numpy")


def have_numba() -> bool:
    return _numba is not None


@lru_cache(maxsize=32)
def vertex_subset(num_vertices: int, stride: int = 1, count: int = 0) -> np.ndarray | None:
    """Indices of the vertices the mesh gate uses, or None for all of them.

    Every ``stride``-th vertex; then, if ``0 < count`` < that many, ``count`` of them spread
    evenly over the index range (fixed topology: the same spots in every detection).
    """
    if stride == 1 and (count <= 0 or count >= num_vertices):
        return None
    idx = np.arange(0, num_vertices, stride, dtype=np.int64)
    if 0 < count < idx.size:
        idx = idx[np.unique(np.linspace(0, idx.size - 1, count).round().astype(np.int64))]
    idx.setflags(write=False)
    return idx


@lru_cache(maxsize=32)
def block_order(n: int) -> np.ndarray:
    """(B,2) int64 [start, end) point blocks of ``range(n)`` in the fixed shuffled order."""
    starts = np.arange(0, n, BLOCK, dtype=np.int64)
    blocks = np.stack([starts, np.minimum(starts + BLOCK, n)], axis=1)
    blocks = blocks[np.random.default_rng(ORDER_SEED).permutation(len(blocks))]
    blocks.setflags(write=False)
    return blocks


@lru_cache(maxsize=32)
def _chunk_indices(n: int) -> tuple[np.ndarray, ...]:
    """Point indices of each early-exit chunk (numpy reference path)."""
    blocks = block_order(n)
    return tuple(np.concatenate([np.arange(s, e) for s, e in blocks[c:c + CHUNK_BLOCKS]])
            for c in range(0, len(blocks), CHUNK_BLOCKS))


def epipolar_sums(xa: np.ndarray, xb: np.ndarray, F: np.ndarray, ia: np.ndarray, jb: np.ndarray,
                  tau: float, symmetric: bool = True, early_exit: bool = True,
                  backend: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Distance sums of the detection pairs (ia[s] in a, jb[s] in b).

    xa (Na,n,2), xb (Nb,n,2) rectified px (float32 or float64, point k = same body spot);
    F (3,3) a->b; ia, jb (S,) int detection indices. Returns (sums (S,) px, evaluated (S,) int
    points summed). Reject a pair iff ``sums >= tau * n`` (identical with or without early
    exit); with early exit a rejected pair's sum is a partial (lower-bound) sum.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if xa.ndim != 3 or xb.ndim != 3 or xa.shape[1:] != xb.shape[1:] or xa.shape[2] != 2:
        raise ValueError(f"epipolar points: expected (Na,n,2) and (Nb,n,2), got {xa.shape} "
                         f"and {xb.shape}")
    ia = np.ascontiguousarray(ia, dtype=np.int64)
    jb = np.ascontiguousarray(jb, dtype=np.int64)
    n = xa.shape[1]
    limit = float(tau) * n if early_exit else np.inf
    if ia.shape != jb.shape or ia.ndim != 1:
        raise ValueError(f"epipolar pairs: ia, jb must be equal-length 1D, got {ia.shape}, "
                         f"{jb.shape}")
    if ia.size == 0 or n == 0:
        return np.zeros(ia.size), np.zeros(ia.size, dtype=np.int64)
    # the kernel runs without bounds checks
    if ia.min() < 0 or ia.max() >= xa.shape[0] or jb.min() < 0 or jb.max() >= xb.shape[0]:
        raise ValueError("epipolar pairs: detection index out of range")
    use_numba = backend == "numba" or (backend == "auto" and _numba is not None)
    if use_numba:
        if _numba is None:
            raise ValueError("backend: 'numba' requested but numba is not installed")
        if xa.dtype != xb.dtype or xa.dtype not in (np.float32, np.float64):
            xa, xb = xa.astype(np.float64), xb.astype(np.float64)
        kernel = _numba_kernel()
        return kernel(np.ascontiguousarray(xa).reshape(xa.shape[0], -1),
                      np.ascontiguousarray(xb).reshape(xb.shape[0], -1),
                      np.ascontiguousarray(F, dtype=np.float64).ravel(), ia, jb, block_order(n),
                      CHUNK_BLOCKS, limit, bool(symmetric))
    return _numpy_sums(xa, xb, np.asarray(F, dtype=np.float64), ia, jb, limit, bool(symmetric))


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernels for float32 mesh vertices and
    float64 keypoints now, so a node's first frame does not pay for it. No-op without numba."""
    if _numba is None:
        return
    F = np.eye(3)[[1, 0, 2]]
    one = np.zeros(1, dtype=np.int64)
    for dtype in (np.float32, np.float64):
        x = np.ones((1, BLOCK, 2), dtype=dtype)
        for symmetric in (True, False):
            epipolar_sums(x, x, F, one, one, 1.0, symmetric, True, "numba")


def point_distances(xa: np.ndarray, xb: np.ndarray, F: np.ndarray, symmetric: bool) -> np.ndarray:
    """(...,n) per-point distances (px) of corresponding points xa, xb (...,n,2) under F (a->b)."""
    xa = np.asarray(xa, dtype=np.float64)
    xb = np.asarray(xb, dtype=np.float64)
    ua, va, ub, vb = xa[..., 0], xa[..., 1], xb[..., 0], xb[..., 1]
    l0 = F[0, 0] * ua + F[0, 1] * va + F[0, 2]
    l1 = F[1, 0] * ua + F[1, 1] * va + F[1, 2]
    l2 = F[2, 0] * ua + F[2, 1] * va + F[2, 2]
    e = np.abs(ub * l0 + vb * l1 + l2)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = e / np.sqrt(l0 * l0 + l1 * l1)
        if symmetric:
            m0 = F[0, 0] * ub + F[1, 0] * vb + F[2, 0]
            m1 = F[0, 1] * ub + F[1, 1] * vb + F[2, 1]
            d = 0.5 * (d + e / np.sqrt(m0 * m0 + m1 * m1))
    return np.where(np.isnan(d), np.inf, d)


def _numpy_sums(xa, xb, F, ia, jb, limit, symmetric):
    """Reference path: all pairs of a chunk at once, chunks in the fixed order, early exit."""
    S = ia.size
    sums = np.zeros(S)
    evaluated = np.zeros(S, dtype=np.int64)
    alive = np.arange(S)
    for idx in _chunk_indices(xa.shape[1]):
        A = xa[ia[alive, None], idx[None, :]]
        B = xb[jb[alive, None], idx[None, :]]
        sums[alive] += point_distances(A, B, F, symmetric).sum(axis=1)
        evaluated[alive] += idx.size
        alive = alive[sums[alive] < limit]
        if alive.size == 0:
            break
    return sums, evaluated


@lru_cache(maxsize=1)
def _numba_kernel():
    """Compile (or load from the on-disk cache) the numba kernel on first use."""
    nb = _numba
    # no nnan/ninf fast-math flags: inf (point at the epipole) must survive; error_model numpy
    # removes the ZeroDivisionError branch that would block SIMD vectorisation
    flags = {"reassoc", "contract", "arcp", "nsz"}

    @nb.njit(cache=True, fastmath=flags, error_model="numpy", boundscheck=False, nogil=True)
    def block_sum(a, b, f):
        part = 0.0
        for k in range(a.shape[0] // 2):
            ua = np.float64(a[2 * k])
            va = np.float64(a[2 * k + 1])
            ub = np.float64(b[2 * k])
            vb = np.float64(b[2 * k + 1])
            l0 = f[0] * ua + f[1] * va + f[2]
            l1 = f[3] * ua + f[4] * va + f[5]
            l2 = f[6] * ua + f[7] * va + f[8]
            e = abs(ub * l0 + vb * l1 + l2)
            part += e / np.sqrt(l0 * l0 + l1 * l1)
        return part

    # block_sum_sym repeats block_sum's forward-line code on purpose: one branch-free loop per
    # mode is what numba vectorises (an `if symmetric` inside the hot loop would block SIMD)
    @nb.njit(cache=True, fastmath=flags, error_model="numpy", boundscheck=False, nogil=True)
    def block_sum_sym(a, b, f):
        part = 0.0
        for k in range(a.shape[0] // 2):
            ua = np.float64(a[2 * k])
            va = np.float64(a[2 * k + 1])
            ub = np.float64(b[2 * k])
            vb = np.float64(b[2 * k + 1])
            l0 = f[0] * ua + f[1] * va + f[2]
            l1 = f[3] * ua + f[4] * va + f[5]
            l2 = f[6] * ua + f[7] * va + f[8]
            e = abs(ub * l0 + vb * l1 + l2)
            m0 = f[0] * ub + f[3] * vb + f[6]
            m1 = f[1] * ub + f[4] * vb + f[7]
            part += e * (1.0 / np.sqrt(l0 * l0 + l1 * l1) + 1.0 / np.sqrt(m0 * m0 + m1 * m1))
        return 0.5 * part

    @nb.njit(cache=True, error_model="numpy", boundscheck=False, nogil=True)
    def sums_kernel(xa, xb, f, ia, jb, blocks, chunk_blocks, limit, symmetric):
        S = ia.shape[0]
        sums = np.zeros(S)
        evaluated = np.zeros(S, dtype=np.int64)
        nblocks = blocks.shape[0]
        for s in range(S):
            a = xa[ia[s]]
            b = xb[jb[s]]
            total = 0.0
            q = 0
            while q < nblocks:
                qe = min(q + chunk_blocks, nblocks)
                part = 0.0
                for r in range(q, qe):
                    lo = 2 * blocks[r, 0]
                    hi = 2 * blocks[r, 1]
                    if symmetric:
                        part += block_sum_sym(a[lo:hi], b[lo:hi], f)
                    else:
                        part += block_sum(a[lo:hi], b[lo:hi], f)
                    evaluated[s] += blocks[r, 1] - blocks[r, 0]
                if part != part:  # NaN: undefined line -> cannot pass
                    part = np.inf
                total += part
                q = qe
                if total >= limit:
                    break
            sums[s] = total
        return sums, evaluated

    return sums_kernel
