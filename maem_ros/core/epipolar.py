"""Epipolar gate kernels: mean point-to-epipolar-line distance between corresponding points.

For a camera pair (a, b) with ``x_b^T F x_a = 0`` (rectified pinhole px) and two detections
whose point k is the same body spot (mesh vertex or keypoint), the per-point distance is

    forward:    d_k = |x_b^T F x_a| / ||(F x_a)_12||                 (x_b to the line of x_a in b)
    symmetric:  d_k = 0.5 |x_b^T F x_a| (1/||(F x_a)_12|| + 1/||(F^T x_b)_12||)

A point missing in either detection (NaN coordinate; q4 wire code 65535) takes no part: the
pair's mean is over the ``used`` points both detections have, and a pair is rejected when
``sum_k d_k >= tau * used`` (mean >= tau px; no common point at all rejects it).

Exact early exit: d_k >= 0, so once a partial sum (points walked in one fixed shuffled order,
in chunks) reaches ``tau * (n - missing so far)`` -- an upper bound of tau * used -- the full
sum reaches tau * used too and the pair is rejected; accepted pairs are always summed
completely (their sum / used is the exact mean). Floating-point addition of non-negative
numbers is monotone, so with the same chunking the decision equals the full sum's.

The numba kernel computes each point's inverse line norms once per detection and camera pair
(lazily, per block, on the first candidate pair that walks the block) and reuses them for every
other candidate of that detection, so a pair costs one bilinear form per point. It reads each
camera's points where they are (:class:`PointRows`: a strided PointCloud2 field or a
contiguous array, float32 or float64), without copies. The numpy reference uses the same
order and chunking. A point at the epipole has an undefined line: its distance is inf (or NaN,
mapped to inf), which rejects the pair.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

#: points per contiguous block (SIMD-friendly, long enough that the per-block overhead stays
#: small); blocks are visited in a fixed shuffled order
BLOCK = 512
#: blocks per early-exit check (512 points)
CHUNK_BLOCKS = 1
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


@dataclass(frozen=True)
class PointRows:
    """One camera's points as the kernel reads them: point k of detection i is
    ``(flat[rows[i] + 2k], flat[rows[i] + 2k + 1])`` rectified px (NaN = missing).

    flat: 1D C-contiguous float32/float64 (may span other message fields between rows, never
    read); rows (N,) int64 element offsets; n points per detection.
    """

    flat: np.ndarray
    rows: np.ndarray
    n: int

    @property
    def count(self) -> int:
        return int(self.rows.size)


def point_rows(x: np.ndarray | PointRows) -> PointRows:
    """(N,n,2) points -> :class:`PointRows`, zero-copy when each detection's (n,2) block is
    contiguous and aligned (a contiguous array, or a field view of a PointCloud2 with one
    detection per point); otherwise one contiguous float64 copy."""
    if isinstance(x, PointRows):
        return x
    x = np.asarray(x)
    if x.ndim != 3 or x.shape[2] != 2:
        raise ValueError(f"epipolar points: expected (N,n,2), got {x.shape}")
    N, n = int(x.shape[0]), int(x.shape[1])
    if x.dtype not in (np.float32, np.float64) or not x.dtype.isnative:
        x = x.astype(np.float64)
    item = x.dtype.itemsize
    inner_ok = n <= 1 or x.strides[1] == 2 * item
    if N and n and not (inner_ok and x.strides[2] == item and x.strides[0] % item == 0
                        and x.strides[0] >= 0 and x.ctypes.data % item == 0):
        x = np.ascontiguousarray(x)
    if N == 0 or n == 0:
        return PointRows(np.zeros(max(2 * n, 1), dtype=x.dtype), np.zeros(N, dtype=np.int64), n)
    step = x.strides[0] // item if N > 1 else 2 * n
    span = (N - 1) * step + 2 * n
    flat = np.lib.stride_tricks.as_strided(x, shape=(span,), strides=(item,), writeable=False)
    return PointRows(flat, np.arange(N, dtype=np.int64) * step, n)


def epipolar_sums(xa: np.ndarray | PointRows, xb: np.ndarray | PointRows, F: np.ndarray,
                  ia: np.ndarray, jb: np.ndarray, tau: float, symmetric: bool = True,
                  early_exit: bool = True, backend: str = "auto"
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Distance sums of the detection pairs (ia[s] in a, jb[s] in b).

    xa (Na,n,2), xb (Nb,n,2) rectified px (float32 or float64, point k = same body spot, NaN =
    missing) or their :class:`PointRows`; F (3,3) a->b; ia, jb (S,) int detection indices.
    Returns (sums (S,) px, used (S,) int points summed). Reject a pair iff
    ``sums >= tau * used`` (identical with or without early exit). An accepted pair's sum is
    complete (sum / used = its mean distance); with early exit a rejected pair's sum and count
    are partial.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    ra, rb = point_rows(xa), point_rows(xb)
    if ra.n != rb.n:
        raise ValueError(f"epipolar points: expected (Na,n,2) and (Nb,n,2), got n={ra.n} "
                         f"and n={rb.n}")
    ia = np.ascontiguousarray(ia, dtype=np.int64)
    jb = np.ascontiguousarray(jb, dtype=np.int64)
    n = ra.n
    if ia.shape != jb.shape or ia.ndim != 1:
        raise ValueError(f"epipolar pairs: ia, jb must be equal-length 1D, got {ia.shape}, "
                         f"{jb.shape}")
    if ia.size == 0 or n == 0:
        return np.zeros(ia.size), np.zeros(ia.size, dtype=np.int64)
    # the kernel runs without bounds checks
    if ia.min() < 0 or ia.max() >= ra.count or jb.min() < 0 or jb.max() >= rb.count:
        raise ValueError("epipolar pairs: detection index out of range")
    tau_eff = float(tau) if early_exit else np.inf
    F = np.ascontiguousarray(F, dtype=np.float64)
    use_numba = backend == "numba" or (backend == "auto" and _numba is not None)
    if not use_numba:
        return _numpy_sums(ra, rb, F, ia, jb, tau_eff, bool(symmetric))
    if _numba is None:
        raise ValueError("backend: 'numba' requested but numba is not installed")
    fa, fb = ra.flat, rb.flat
    if fa.dtype != fb.dtype:
        fa, fb = fa.astype(np.float64), fb.astype(np.float64)
    blocks = block_order(n)
    scale = np.linalg.norm(F)  # distances do not depend on F's scale; unit norm for inv_sqrt
    F = F / scale if scale > 0 else F
    wa, wb, done_a, done_b = _workspace(ra.count, rb.count, n, len(blocks))
    return _numba_kernel()(fa, ra.rows, fb, rb.rows, F.ravel(), ia, jb, blocks, CHUNK_BLOCKS,
                           tau_eff, bool(symmetric), wa, wb, done_a, done_b)


_LOCAL = threading.local()


def _workspace(na: int, nb: int, n: int, nblocks: int):
    """Per-thread reusable weight caches (no page faults per call) and fresh 'done' flags."""
    buf = getattr(_LOCAL, "weights", None)
    need = (na + nb) * n
    if buf is None or buf.size < need:
        buf = _LOCAL.weights = np.empty(max(need, 1))
    wa = buf[:na * n].reshape(na, n)
    wb = buf[na * n:need].reshape(nb, n)
    return wa, wb, np.zeros((na, nblocks), np.bool_), np.zeros((nb, nblocks), np.bool_)


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
    """(...,n) per-point distances (px) of corresponding points xa, xb (...,n,2) under F (a->b).

    NaN where either point is missing (a NaN coordinate); inf for a point at the epipole.
    """
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
    missing = np.isnan(ua + va + ub + vb)
    return np.where(missing, np.nan, np.where(np.isnan(d), np.inf, d))


def _numpy_sums(ra: PointRows, rb: PointRows, F: np.ndarray, ia: np.ndarray, jb: np.ndarray,
                tau: float, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    """Reference path: all pairs of a chunk at once, chunks in the fixed order, early exit."""
    S = ia.size
    sums = np.zeros(S)
    used = np.zeros(S, dtype=np.int64)
    seen = 0
    alive = np.arange(S)
    for idx in _chunk_indices(ra.n):
        cols = 2 * idx[None, :]
        oa, ob = ra.rows[ia[alive], None] + cols, rb.rows[jb[alive], None] + cols
        A = np.stack([ra.flat[oa], ra.flat[oa + 1]], axis=-1)
        B = np.stack([rb.flat[ob], rb.flat[ob + 1]], axis=-1)
        d = point_distances(A, B, F, symmetric)
        present = ~np.isnan(d)
        sums[alive] += np.where(present, d, 0.0).sum(axis=1)
        used[alive] += present.sum(axis=1)
        seen += idx.size
        # used + (points still to come) bounds the final count from above
        with np.errstate(invalid="ignore"):  # inf * 0 without early exit: NaN, not < anything
            alive = alive[sums[alive] < tau * (used[alive] + (ra.n - seen))]
        if alive.size == 0:
            break
    return sums, used


@lru_cache(maxsize=1)
def _numba_kernel():
    """Compile (or load from the on-disk cache) the numba kernel on first use."""
    nb = _numba
    # no nnan/ninf fast-math flags: NaN (missing point) and inf (point at the epipole) must
    # survive; error_model numpy removes the ZeroDivisionError branch that blocks SIMD
    flags = {"reassoc", "contract", "arcp", "nsz"}
    jit = nb.njit(cache=True, fastmath=flags, error_model="numpy", boundscheck=False,
                  nogil=True)

    @jit
    def inv_sqrt(q):
        """1/sqrt(q) to ~1e-13 relative: a float32 estimate (the float64 sqrt and division
        units are the kernel's bottleneck; float32 ones do twice the lanes) refined by one
        Newton step in float64. inf at q = 0 (the epipole), NaN for NaN (a missing point).
        F has unit norm, so q < 1e7 and the estimate is exact to float32 precision down to
        q = 1e-37 (a point ~1e-15 px from the epipole); smaller q are clamped there."""
        y = np.float64(np.float32(1.0) / np.sqrt(np.float32(max(q, 1e-37))))
        y = y * (1.5 - 0.5 * q * y * y)
        return y if q != 0.0 else np.inf

    @jit
    def fill_a(a, f, w, half):
        """w[k] = half / ||(F x_a)_12|| for a block's points a (2m,) (NaN where x_a is missing)."""
        for k in range(w.shape[0]):
            ua = np.float64(a[2 * k])
            va = np.float64(a[2 * k + 1])
            l0 = f[0] * ua + f[1] * va + f[2]
            l1 = f[3] * ua + f[4] * va + f[5]
            w[k] = half * inv_sqrt(l0 * l0 + l1 * l1)

    @jit
    def fill_b(b, f, w, symmetric):
        """w[k] = 0.5 / ||(F^T x_b)_12|| (symmetric) or 0 (forward), NaN where x_b is missing."""
        if symmetric:
            for k in range(w.shape[0]):
                ub = np.float64(b[2 * k])
                vb = np.float64(b[2 * k + 1])
                m0 = f[0] * ub + f[3] * vb + f[6]
                m1 = f[1] * ub + f[4] * vb + f[7]
                w[k] = 0.5 * inv_sqrt(m0 * m0 + m1 * m1)
        else:
            for k in range(w.shape[0]):
                w[k] = (np.float64(b[2 * k]) + np.float64(b[2 * k + 1])) * 0.0  # 0 or NaN

    @jit
    def block_pair(a, b, f, wa, wb):
        """(sum of d_k, points used) over a block; d_k = |x_b^T F x_a| (wa_k + wb_k)."""
        part = 0.0
        used = 0
        for k in range(wa.shape[0]):
            ua = np.float64(a[2 * k])
            va = np.float64(a[2 * k + 1])
            ub = np.float64(b[2 * k])
            vb = np.float64(b[2 * k + 1])
            l0 = f[0] * ua + f[1] * va + f[2]
            l1 = f[3] * ua + f[4] * va + f[5]
            l2 = f[6] * ua + f[7] * va + f[8]
            w = wa[k] + wb[k]
            d = abs(ub * l0 + vb * l1 + l2) * w
            # w is NaN iff a point is missing; at the epipole it is inf and d NaN or inf
            present = w == w
            part += d if present else 0.0
            used += np.int64(present)  # an int64, not a bool, keeps the loop vectorised
        return part, used

    @nb.njit(cache=True, error_model="numpy", boundscheck=False, nogil=True)
    def sums_kernel(fa, rows_a, fb, rows_b, f, ia, jb, blocks, chunk_blocks, tau, symmetric,
                    wa, wb, done_a, done_b):
        S = ia.shape[0]
        n = wa.shape[1]
        half_a = 0.5 if symmetric else 1.0
        sums = np.zeros(S)
        used = np.zeros(S, dtype=np.int64)
        nblocks = blocks.shape[0]
        for s in range(S):
            i = ia[s]
            j = jb[s]
            a = fa[rows_a[i]:rows_a[i] + 2 * n]
            b = fb[rows_b[j]:rows_b[j] + 2 * n]
            total = 0.0
            count = 0
            seen = 0
            q = 0
            while q < nblocks:
                qe = min(q + chunk_blocks, nblocks)
                part = 0.0
                for r in range(q, qe):
                    lo = blocks[r, 0]
                    hi = blocks[r, 1]
                    if not done_a[i, r]:
                        fill_a(a[2 * lo:2 * hi], f, wa[i, lo:hi], half_a)
                        done_a[i, r] = True
                    if not done_b[j, r]:
                        fill_b(b[2 * lo:2 * hi], f, wb[j, lo:hi], symmetric)
                        done_b[j, r] = True
                    p, c = block_pair(a[2 * lo:2 * hi], b[2 * lo:2 * hi], f, wa[i, lo:hi],
                                      wb[j, lo:hi])
                    part += p
                    count += c
                    seen += hi - lo
                if part != part:  # NaN: undefined line -> cannot pass
                    part = np.inf
                total += part
                q = qe
                # count + points still to come bounds the final count from above
                if total >= tau * (count + (n - seen)):
                    break
            sums[s] = total
            used[s] = count
        return sums, used

    return sums_kernel
