"""Epipolar gate kernels: mean point-to-epipolar-line distance between corresponding points.

For a camera pair (a, b) with ``x_b^T F x_a = 0`` (rectified pinhole px) and two detections
whose point k is the same body spot (mesh vertex or keypoint), the per-point distance is

    forward:    d_k = |x_b^T F x_a| / ||(F x_a)_12||                 (x_b to the line of x_a in b)
    symmetric:  d_k = 0.5 |x_b^T F x_a| (1/||(F x_a)_12|| + 1/||(F^T x_b)_12||)

A point missing in either detection (NaN coordinate; q4 wire code 65535) takes no part: the
pair's mean is over the ``used`` points both detections have, and a pair is rejected when
``sum_k d_k >= tau * used`` (mean >= tau px; no common point at all rejects it).

Exact early exit: d_k >= 0, so once a partial sum (points walked in fixed blocks of BLOCK
points, the blocks in one fixed shuffled order) reaches ``tau * (n - missing so far)`` -- an
upper bound of tau * used -- the full sum reaches tau * used too and the pair is rejected;
accepted pairs are always summed completely. Floating-point addition of non-negative numbers is
monotone, so the decision equals the full sum's.

The numpy reference computes every distance in float64. The numba kernel takes every pair of
a frame in one call (:func:`frame_sums`: all camera pairs; each detection's centre and block
coordinate ranges computed once), blocks outermost, so each detection's block is read from
memory once for all its candidate pairs. It fuses everything per point (the line, both norms
and the distance), and two pairs of one detection in one camera pair run in one loop that
computes that detection's lines and weights once. By default (``precision "mixed"``) it runs
float32 SIMD (twice the lanes of float64) on points centred on each detection (u - c,
integer c; the bilinear form loses no digits to the px offset) with a rigorous bound E of the
block sum's rounding error, from float32 unit roundoff u = 2^-24:

    E = (1 + 1e-3) [10 u B h sum w + 8 u h L sum |e| w^2 + (2^-20 + (BLOCK + 8) u) sum d]

(e the bilinear form of the centred points under the float32 F' = T_b^T F T_a (F of unit
norm), w = w_a + w_b and h = 1/2 (symmetric) or w = w_a and h = 1 (forward), w_a, w_b the
reciprocal line norms, B = [|u_b|,|v_b|,1] |F'| [|u_a|,|v_a|,1]^T from the block's coordinate
range, L = max(L_a, L_b) the same bound of the lines' first two coefficients; terms: rounding
of e, of the line norms (through their coefficients and the 2^-20 reciprocal square root;
sum |e| (w_a^2 + w_b^2) <= sum |e| w^2), and of BLOCK float32 additions; E does not depend on
F' 's scale). A pair is rejected early when ``sum - E >= tau * (used + still to come)``,
accepted when ``sum + E < tau * used``, rejected when ``sum - E >= tau * used``; otherwise (the
bound cannot settle it; in practice never) it is recomputed in float64. Blocks with a missing
point or a point at (or very near) the epipole are summed in float64. So the decisions are
those of the float64 sums; an accepted pair's mean carries an error below E / used (~1e-7
relative in practice; ``precision "float64"`` gives it to ~1e-13). The kernel reads each
camera's points where they are (:class:`PointRows`: a strided PointCloud2 field or a
contiguous array, float32 or float64; float64 points are summed in float64), without copies.
A point at the epipole has an undefined line: its distance is inf (or NaN, mapped to inf),
which rejects the pair.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import Mapping

import numpy as np

#: points per contiguous block (SIMD-friendly, long enough that the per-block overhead stays
#: small); blocks are visited in a fixed shuffled order
BLOCK = 1024
#: a point whose line has ||(F x)_12|| <= EPIPOLE_NORM ||F|| is at the epipole (its line is
#: rounding noise): distance inf, the pair is rejected. ~1e-6 px from the epipole of a
#: typical pixel F; one definition for every backend and precision
EPIPOLE_NORM = 1e-12
#: seed of the fixed block order (any fixed value; part of the definition of "the order")
ORDER_SEED = 20240611

try:  # numba is optional: the numpy reference gives the same decisions, only slower
    import numba as _numba
except ImportError:  # pragma: no cover - exercised only without numba
    _numba = None

BACKENDS = ("auto", "numba", "numpy")
PRECISIONS = ("mixed", "float64")


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
def _block_indices(n: int) -> tuple[np.ndarray, ...]:
    """Point indices of each block of :func:`block_order` (numpy reference path)."""
    return tuple(np.arange(s, e) for s, e in block_order(n))


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
                  early_exit: bool = True, backend: str = "auto", precision: str = "mixed"
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Distance sums of the detection pairs (ia[s] in a, jb[s] in b) of one camera pair.

    xa (Na,n,2), xb (Nb,n,2) rectified px (float32 or float64, point k = same body spot, NaN =
    missing) or their :class:`PointRows`; F (3,3) a->b; ia, jb (S,) int detection indices.
    Returns (sums (S,) px, used (S,) int points summed): :func:`frame_sums` of one camera pair.
    """
    ia = np.asarray(ia)
    return frame_sums({0: point_rows(xa), 1: point_rows(xb)}, {(0, 1): F},
                      np.zeros(ia.shape, np.int64), ia, np.ones(ia.shape, np.int64), jb, tau,
                      symmetric, early_exit, backend, precision)


def frame_sums(points: Mapping[int, np.ndarray | PointRows],
               F: Mapping[tuple[int, int], np.ndarray], cam_a: np.ndarray, det_a: np.ndarray,
               cam_b: np.ndarray, det_b: np.ndarray, tau: float, symmetric: bool = True,
               early_exit: bool = True, backend: str = "auto", precision: str = "mixed"
               ) -> tuple[np.ndarray, np.ndarray]:
    """Distance sums of the detection pairs of every camera pair of a frame, in one kernel call.

    points[c]: camera c's (N,n,2) rectified px (float32 or float64, point k = same body spot,
    NaN = missing) or :class:`PointRows` (read in place); F[(a, b)] (3,3) with
    ``x_b^T F x_a = 0``; pair s is detection det_a[s] of camera cam_a[s] against det_b[s] of
    camera cam_b[s]. Returns (sums (S,) px, used (S,) int points summed). Reject a pair iff
    ``sums >= tau * used`` (identical with or without early exit). An accepted pair's sum is
    complete (sum / used = its mean distance); with early exit a rejected pair's sum and count
    are partial.

    precision (numba backend, float32 points): ``mixed`` sums float32 SIMD distances with a
    rigorous bound of their rounding error and re-runs in float64 any pair whose decision the
    bound cannot settle, so the decisions are the float64 ones; an accepted pair's sum is then
    within its bound (~1e-7 relative in practice) of the exact one. ``float64``: every distance
    in float64 (sums to ~1e-13).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {PRECISIONS}, got {precision!r}")
    pairs = [np.ascontiguousarray(v, dtype=np.int64) for v in (cam_a, det_a, cam_b, det_b)]
    if any(v.ndim != 1 or v.shape != pairs[0].shape for v in pairs):
        raise ValueError(f"epipolar pairs: cameras and detections must be equal-length 1D, got "
                         f"{[v.shape for v in pairs]}")
    cam_a, det_a, cam_b, det_b = pairs
    S = cam_a.size
    cams = sorted(set(np.unique(cam_a).tolist()) | set(np.unique(cam_b).tolist()))
    missing = [c for c in cams if c not in points]
    if missing:
        raise ValueError(f"epipolar pairs: no points for camera(s) {missing}")
    rows = {c: point_rows(points[c]) for c in cams}
    sizes = {rows[c].n for c in cams}
    if len(sizes) > 1:
        raise ValueError(f"epipolar points: expected (N,n,2) with one n for every camera, got "
                         f"n={sorted(sizes)}")
    n = sizes.pop() if sizes else 0
    if S == 0 or n == 0:
        return np.zeros(S), np.zeros(S, dtype=np.int64)
    for cam, det in ((cam_a, det_a), (cam_b, det_b)):
        count = np.array([rows[c].count for c in cams])[np.searchsorted(cams, cam)]
        if det.min() < 0 or np.any(det >= count):  # the kernel runs without bounds checks
            raise ValueError("epipolar pairs: detection index out of range")
    groups = np.unique(cam_a * (max(cams) + 1) + cam_b, return_inverse=True)
    keys, which = groups[0], groups[1].reshape(-1)
    Fs = []
    for k in keys.tolist():
        a, b = divmod(k, max(cams) + 1)
        if (a, b) not in F:
            raise ValueError(f"epipolar pairs: no fundamental matrix for camera pair {(a, b)}")
        Fs.append(np.asarray(F[(a, b)], dtype=np.float64))
    use_numba = backend == "numba" or (backend == "auto" and _numba is not None)
    if not use_numba:
        sums = np.zeros(S)
        used = np.zeros(S, dtype=np.int64)
        for g, Fg in enumerate(Fs):
            s = np.flatnonzero(which == g)
            sums[s], used[s] = _numpy_sums(rows[int(cam_a[s[0]])], rows[int(cam_b[s[0]])],
                                           Fg, det_a[s], det_b[s],
                                           float(tau) if early_exit else np.inf, bool(symmetric))
        return sums, used
    if _numba is None:
        raise ValueError("backend: 'numba' requested but numba is not installed")
    return _numba_frame_sums(rows, cams, Fs, which, cam_a, det_a, cam_b, det_b, n, float(tau),
                             bool(symmetric), bool(early_exit), precision)


def _numba_frame_sums(rows: dict[int, PointRows], cams: list[int], Fs: list[np.ndarray],
                      which: np.ndarray, cam_a: np.ndarray, det_a: np.ndarray,
                      cam_b: np.ndarray, det_b: np.ndarray, n: int, tau: float,
                      symmetric: bool, early_exit: bool, precision: str
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The numba kernel on the pairs of a frame: detections numbered once (each one's centre and
    block ranges computed once for all its pairs), pairs ordered by their a-side detection."""
    flats = [rows[c].flat for c in cams]
    if len({f.dtype for f in flats}) > 1:  # mixed float32/float64 cameras: all in float64
        flats = [f.astype(np.float64) for f in flats]
    # float64 points (keypoints: few per detection) always take the float64 path
    mixed = (precision == "mixed" and flats[0].dtype == np.float32 and _rsqrt_within_bound())
    slot = np.searchsorted(cams, np.concatenate([cam_a, cam_b]))
    offsets = np.concatenate([[0], np.cumsum([rows[c].count for c in cams])])
    key = offsets[slot] + np.concatenate([det_a, det_b])
    dets, idx = np.unique(key, return_inverse=True)
    det_slot = np.searchsorted(offsets, dets, side="right") - 1
    det_row = np.concatenate([rows[c].rows for c in cams])[dets]
    S = cam_a.size
    pa, pb = idx[:S], idx[S:]
    # distances do not depend on F's scale; unit norm for the error bounds
    unit = np.stack(Fs)
    norm = np.sqrt((unit * unit).sum(axis=(1, 2)))
    unit = unit / np.where(norm > 0, norm, 1.0)[:, None, None]
    # a detection's pairs one after another (its block stays hot), those of one camera pair
    # together (they share its lines)
    order = np.lexsort((pb, which, pa))
    # each detection's first coordinate as an address: flats stay referenced during the call
    base = np.array([f.__array_interface__["data"][0] for f in flats], dtype=np.int64)
    det_addr = base[det_slot] + det_row * flats[0].dtype.itemsize
    sums, used = _numba_kernel()(flats[0], det_addr, unit.reshape(-1, 9),
                                 np.ascontiguousarray(which[order], dtype=np.int64),
                                 np.ascontiguousarray(pa[order]), np.ascontiguousarray(pb[order]),
                                 block_order(n), n, tau, early_exit, symmetric, mixed)
    out_sums = np.empty(S)
    out_used = np.empty(S, dtype=np.int64)
    out_sums[order] = sums
    out_used[order] = used
    return out_sums, out_used


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernels for float32 mesh vertices and
    float64 keypoints now, so a node's first frame does not pay for it. No-op without numba."""
    if _numba is None:
        return
    F = np.eye(3)[[1, 0, 2]]
    one = np.zeros(1, dtype=np.int64)
    for dtype in (np.float32, np.float64):
        x = np.ones((1, BLOCK, 2), dtype=dtype)
        for precision in PRECISIONS:
            epipolar_sums(x, x, F, one, one, 1.0, True, True, "numba", precision)


def point_distances(xa: np.ndarray, xb: np.ndarray, F: np.ndarray, symmetric: bool) -> np.ndarray:
    """(...,n) per-point distances (px) of corresponding points xa, xb (...,n,2) under F (a->b).

    NaN where either point is missing (a NaN coordinate); inf for a point at the epipole
    (EPIPOLE_NORM).
    """
    xa = np.asarray(xa, dtype=np.float64)
    xb = np.asarray(xb, dtype=np.float64)
    F = np.asarray(F, dtype=np.float64)
    F = F / np.linalg.norm(F)
    ua, va, ub, vb = xa[..., 0], xa[..., 1], xb[..., 0], xb[..., 1]
    l0 = F[0, 0] * ua + F[0, 1] * va + F[0, 2]
    l1 = F[1, 0] * ua + F[1, 1] * va + F[1, 2]
    l2 = F[2, 0] * ua + F[2, 1] * va + F[2, 2]
    e = np.abs(ub * l0 + vb * l1 + l2)
    q = l0 * l0 + l1 * l1
    at_epipole = q <= EPIPOLE_NORM ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = e / np.sqrt(q)
        if symmetric:
            m0 = F[0, 0] * ub + F[1, 0] * vb + F[2, 0]
            m1 = F[0, 1] * ub + F[1, 1] * vb + F[2, 1]
            qb = m0 * m0 + m1 * m1
            at_epipole |= qb <= EPIPOLE_NORM ** 2
            d = 0.5 * (d + e / np.sqrt(qb))
    missing = np.isnan(ua + va + ub + vb)
    return np.where(missing, np.nan, np.where(at_epipole | np.isnan(d), np.inf, d))


def _numpy_sums(ra: PointRows, rb: PointRows, F: np.ndarray, ia: np.ndarray, jb: np.ndarray,
                tau: float, symmetric: bool) -> tuple[np.ndarray, np.ndarray]:
    """Reference path: all pairs of a block at once, blocks in the fixed order, early exit."""
    S = ia.size
    sums = np.zeros(S)
    used = np.zeros(S, dtype=np.int64)
    seen = 0
    alive = np.arange(S)
    for idx in _block_indices(ra.n):
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


#: float32 unit roundoff
_U32 = 2.0 ** -24
#: relative error bound of a float32 1/sqrt (hardware estimate, |rel err| <= 1.5 * 2^-12, plus
#: one Newton step in float32: ~3 * 2^-24 + 1.7 * 2^-24; 2^-20 leaves a margin of ~3)
_RSQRT_ERR = 2.0 ** -20
#: relative slack on the error bound for its own (second-order) rounding
_BOUND_SLACK = 1e-3
#: float32 bit patterns mapped to ordered int32 keys: keys of -inf and +inf (finite in between)
_KEY_NEG_INF = -2139095041
_KEY_POS_INF = 2139095040


@lru_cache(maxsize=1)
def _rsqrt_within_bound() -> bool:
    """Whether the compiled float32 1/sqrt (the instructions LLVM picks for this CPU) is within
    _RSQRT_ERR of the exact value over a sweep of arguments; if not, the mixed kernel's error
    bound would not hold, and "mixed" runs in float64 instead."""
    nb = _numba
    flags = {"reassoc", "contract", "arcp", "nsz", "afn"}  # block32's

    @nb.njit(fastmath=flags, error_model="numpy", boundscheck=False, cache=True)
    def rsqrt32(q, out):
        for k in range(q.shape[0]):  # the same vectorised form as in block32
            out[k] = np.float32(1.0) / np.sqrt(q[k])

    q = np.geomspace(1e-30, 1e30, 200_003).astype(np.float32)
    q = np.concatenate([q, np.random.default_rng(0).uniform(0.5, 2.0, 100_000).astype(np.float32)])
    got = np.empty_like(q)
    rsqrt32(q, got)
    exact = 1.0 / np.sqrt(q.astype(np.float64))
    return bool(np.max(np.abs(got / exact - 1.0)) <= _RSQRT_ERR / 2)


@lru_cache(maxsize=1)
def _numba_kernel():
    """Compile (or load from the on-disk cache) the numba kernels on first use."""
    nb = _numba
    # no nnan/ninf fast-math flags: NaN (missing point) and inf (point at the epipole) must
    # survive; error_model numpy removes the ZeroDivisionError branch that blocks SIMD;
    # reassoc lets the sums vectorise
    flags = {"reassoc", "contract", "arcp", "nsz"}
    opts = dict(cache=True, error_model="numpy", boundscheck=False, nogil=True)
    jit = nb.njit(fastmath=flags, **opts)
    # afn: float32 1/sqrt as the hardware estimate + one Newton step (bounded by _RSQRT_ERR)
    jit32 = nb.njit(fastmath=flags | {"afn"}, **opts)
    plain = nb.njit(**opts)
    # per pair and block helpers: inlined, so the hot loop passes no array views through calls
    inline = nb.njit(inline="always", **opts)

    @nb.extending.intrinsic
    def pointer_like(typingctx, like, address):
        """The int64 address as a pointer to like's dtype."""
        sig = nb.types.CPointer(like.dtype)(like, address)

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[1], context.get_value_type(signature.return_type))
        return sig, codegen

    @inline
    def points(like, address, start, count):
        """count coordinates from element start of the detection at address: a view without
        reference counting (a typed list of the cameras' arrays costs ~20 ns per access in the
        hot loop); the caller keeps the arrays alive."""
        return nb.carray(pointer_like(like, address + start * like.itemsize), (count,))

    q_epipole = EPIPOLE_NORM ** 2

    @jit
    def inv_sqrt(q):
        """1/sqrt(q) to ~1e-13 relative: a float32 estimate refined by one Newton step in
        float64 (float64 sqrt and division are the slow units). inf at the epipole
        (q <= EPIPOLE_NORM^2; F has unit norm, so the float32 estimate is in range), NaN for
        NaN."""
        y = np.float64(np.float32(1.0) / np.sqrt(np.float32(max(q, q_epipole))))
        y = y * (1.5 - 0.5 * q * y * y)
        return y if q > q_epipole else np.inf

    @jit
    def block64(a, b, f, ha, symmetric):
        """(sum of d_k, points used) of a block, float64: points a, b (2m,) rectified px, f (9,)
        unit F; missing points (NaN) take no part; a point at the epipole makes the sum
        NaN or inf."""
        part = 0.0
        used = 0
        for k in range(a.shape[0] // 2):
            ua = np.float64(a[2 * k])
            va = np.float64(a[2 * k + 1])
            ub = np.float64(b[2 * k])
            vb = np.float64(b[2 * k + 1])
            l0 = f[0] * ua + f[1] * va + f[2]
            l1 = f[3] * ua + f[4] * va + f[5]
            l2 = f[6] * ua + f[7] * va + f[8]
            w = ha * inv_sqrt(l0 * l0 + l1 * l1)
            if symmetric:
                m0 = f[0] * ub + f[3] * vb + f[6]
                m1 = f[1] * ub + f[4] * vb + f[7]
                w += 0.5 * inv_sqrt(m0 * m0 + m1 * m1)
            d = abs(ub * l0 + vb * l1 + l2) * w
            s = ua + va + ub + vb
            present = s == s
            part += d if present else 0.0
            used += np.int64(present)  # an int64, not a bool, keeps the loop vectorised
        return part, used

    @jit32
    def block32(a, b, c, g, symmetric):
        """float32 sums over a block of complete points, centred (u - c[0], v - c[1]) in a,
        (u - c[2], v - c[3]) in b, g (9,) float32 F of the centred points:
        (sum |e| w, sum w, sum |e| w^2) with e = x_b^T g x_a and w = wa + wb (symmetric) or
        wa, wa = 1/||(g x_a)_12||, wb = 1/||(g^T x_b)_12||."""
        p = s = q = np.float32(0.0)
        for k in range(a.shape[0] // 2):
            ua = a[2 * k] - c[0]
            va = a[2 * k + 1] - c[1]
            ub = b[2 * k] - c[2]
            vb = b[2 * k + 1] - c[3]
            l0 = g[0] * ua + g[1] * va + g[2]
            l1 = g[3] * ua + g[4] * va + g[5]
            l2 = g[6] * ua + g[7] * va + g[8]
            e = abs(ub * l0 + vb * l1 + l2)
            w = np.float32(1.0) / np.sqrt(l0 * l0 + l1 * l1)
            if symmetric:
                m0 = g[0] * ub + g[3] * vb + g[6]
                m1 = g[1] * ub + g[4] * vb + g[7]
                w += np.float32(1.0) / np.sqrt(m0 * m0 + m1 * m1)
            ew = e * w
            p += ew
            s += w
            q += ew * w
        return np.float64(p), np.float64(s), np.float64(q)

    @jit32
    def b_terms(ub, vb, ua, va, l0, l1, wa, g, symmetric):
        """(|e| w, w) of one point of a pair: centred b point (ub, vb), a point (ua, va) with
        its line's first coefficients l0, l1 and weight wa, g (9,) the pair's centred F."""
        e = abs(ub * l0 + vb * l1 + (g[6] * ua + g[7] * va + g[8]))
        m0 = g[0] * ub + g[3] * vb + g[6]
        m1 = g[1] * ub + g[4] * vb + g[7]
        wb = np.float32(1.0) / np.sqrt(m0 * m0 + m1 * m1)
        w = wa + wb if symmetric else wa  # the select keeps the loop branch-free
        return e * w, w

    @jit32
    def block32x2(a, b, d, ca, cb, cd, g, k, symmetric):
        """block32 of two pairs (a, b) under g and (a, d) under k that share a's detection and
        camera pair (g, k have equal rows 0-1): a's lines and weights computed once. ca, cb,
        cd (2,) the centres; returns block32's three sums for each pair."""
        p1 = s1 = q1 = p2 = s2 = q2 = np.float32(0.0)
        for j in range(a.shape[0] // 2):
            ua = a[2 * j] - ca[0]
            va = a[2 * j + 1] - ca[1]
            l0 = g[0] * ua + g[1] * va + g[2]
            l1 = g[3] * ua + g[4] * va + g[5]
            wa = np.float32(1.0) / np.sqrt(l0 * l0 + l1 * l1)
            ew, w = b_terms(b[2 * j] - cb[0], b[2 * j + 1] - cb[1], ua, va, l0, l1, wa, g,
                            symmetric)
            p1 += ew
            s1 += w
            q1 += ew * w
            ew, w = b_terms(d[2 * j] - cd[0], d[2 * j + 1] - cd[1], ua, va, l0, l1, wa, k,
                            symmetric)
            p2 += ew
            s2 += w
            q2 += ew * w
        return ((np.float64(p1), np.float64(s1), np.float64(q1)),
                (np.float64(p2), np.float64(s2), np.float64(q2)))

    @plain
    def block_range(x, ranges, r):
        """(min, max) of all coordinates of a block's float32 points (2m,), cached in
        ranges[r]; (inf, -inf) if one is NaN or inf. Ordered integer keys of the float bits,
        so the min/max reductions vectorise."""
        if ranges[r, 0] == ranges[r, 0]:
            return ranges[r, 0], ranges[r, 1]
        bits = x.view(np.int32)
        lo = np.int32(2147483647)
        hi = np.int32(-2147483648)
        low31 = np.int32(0x7FFFFFFF)
        for k in range(bits.shape[0]):
            b = bits[k]
            # int32 throughout and selects, not min(): the loop vectorises
            key = np.int32(b ^ (np.int32(b >> np.int32(31)) & low31))
            lo = key if key < lo else lo
            hi = key if key > hi else hi
        if lo <= _KEY_NEG_INF or hi >= _KEY_POS_INF:
            ranges[r, 0], ranges[r, 1] = np.inf, -np.inf
        else:
            keys = np.empty(2, dtype=np.int32)
            keys[0] = lo ^ ((lo >> 31) & low31)
            keys[1] = hi ^ ((hi >> 31) & low31)
            vals = keys.view(np.float32)
            ranges[r, 0], ranges[r, 1] = vals[0], vals[1]
        return ranges[r, 0], ranges[r, 1]

    @plain
    def centre(x, n):
        """Integer px near a detection's points (its first complete point; 0 if none)."""
        for k in range(n):
            if x[2 * k] == x[2 * k] and x[2 * k + 1] == x[2 * k + 1]:
                return np.floor(np.float64(x[2 * k]) + 0.5), np.floor(np.float64(x[2 * k + 1]) + 0.5)
        return 0.0, 0.0

    @plain
    def centred_f(f, ca0, ca1, cb0, cb1, g, G):
        """g (9,) float32 T_b^T F T_a: F (f (9,) row-major, unit norm) of the points centred on
        (ca0, ca1) in a and (cb0, cb1) in b; G (3,3) = |g|. Rows 0-1 depend on a's centre only
        (a detection's pairs in one camera pair share them bit for bit), and (g x)_12 =
        (F x)_12, so EPIPOLE_NORM applies in g's units as it is; the error bound does not
        depend on g's scale."""
        h = np.empty((3, 3))
        for r in range(3):
            h[r, 0] = f[3 * r]
            h[r, 1] = f[3 * r + 1]
            h[r, 2] = f[3 * r] * ca0 + f[3 * r + 1] * ca1 + f[3 * r + 2]
        for col in range(3):
            h[2, col] = cb0 * h[0, col] + cb1 * h[1, col] + h[2, col]
        for r in range(3):
            for col in range(3):
                g[3 * r + col] = np.float32(h[r, col])
                G[r, col] = abs(np.float64(g[3 * r + col]))

    @plain
    def block_bound(G, epi, xa0, xa1, xb0, xb1, sums, h):
        """(float32 block sum, upper bound (px) on its distance to the exact sum); xa0, xa1,
        xb0, xb1 bound |u|, |v| of the centred points in a and b (module docstring); epi:
        EPIPOLE_NORM in g's units; h = 0.5 (symmetric) or 1. (inf, inf) when the block must be
        summed in float64."""
        # rows of G times (xa0, xa1, 1), then xb's weights: no loops, no tuple indexing (this
        # runs per pair and block)
        r0 = G[0, 0] * xa0 + G[0, 1] * xa1 + G[0, 2]
        r1 = G[1, 0] * xa0 + G[1, 1] * xa1 + G[1, 2]
        r2 = G[2, 0] * xa0 + G[2, 1] * xa1 + G[2, 2]
        bil = r0 * xb0 + r1 * xb1 + r2
        la = r0 + r1
        lb = (G[0, 0] + G[0, 1]) * xb0 + (G[1, 0] + G[1, 1]) * xb1 + G[2, 0] + G[2, 1]
        lmax = max(la, lb) if h != 1.0 else la
        p, s, q = sums
        # a point at the epipole (float64 rule: ||l_12|| <= EPIPOLE_NORM = epi in g's units)
        # has a float32 line norm within the rounding bound 6 u L of that: its weight, and so
        # the block's weight sum, reaches 1 / (epi + 6 u L); such a block goes to float64
        # (part inf)
        if not s * (epi + 6.0 * _U32 * lmax) * (1.0 + 2.0 * _RSQRT_ERR) < 1.0:
            return np.inf, np.inf
        part = h * p
        # sum |e| (wa^2 + wb^2) <= sum |e| w^2 bounds the line-norm term of both sides
        err = (10.0 * _U32 * bil * h * s + 8.0 * _U32 * h * lmax * q
               + (_RSQRT_ERR + (BLOCK + 8) * _U32) * part)
        return part, err * (1.0 + _BOUND_SLACK)

    @plain
    def pair64(a, b, f, blocks, n, tau, early_exit, ha, symmetric):
        """(sum, used) of one pair in float64, blocks in order, exact early exit."""
        total = 0.0
        count = 0
        seen = 0
        for r in range(blocks.shape[0]):
            lo = blocks[r, 0]
            hi = blocks[r, 1]
            p, c = block64(a[2 * lo:2 * hi], b[2 * lo:2 * hi], f, ha, symmetric)
            total += p if p == p else np.inf  # NaN: undefined line -> cannot pass
            count += c
            seen += hi - lo
            # count + points still to come bounds the final count from above
            if early_exit and total >= tau * (count + (n - seen)):
                break
        return total, count

    @inline
    def pair_bound(G, ra, rb, c, sums3, h):
        """block_bound of a pair from its blocks' coordinate ranges ra, rb (min, max) and its
        centres c (4,)."""
        return block_bound(G, EPIPOLE_NORM, max(abs(ra[1] - c[0]), abs(ra[0] - c[0])),
                           max(abs(ra[1] - c[1]), abs(ra[0] - c[1])),
                           max(abs(rb[1] - c[2]), abs(rb[0] - c[2])),
                           max(abs(rb[1] - c[3]), abs(rb[0] - c[3])), sums3, h)

    @inline
    def settle(s, p, e, ab, bb, f, m, rest, h, symmetric, tau, early_exit, sums, err, used,
               alive):
        """Add pair s's block: the float32 sum p within e, or (e inf: missing points, a point
        at or very near the epipole) the float64 sum of blocks ab, bb; then the exact early
        exit, ``rest`` points still to come."""
        if p < np.inf and e < np.inf:
            sums[s] += p
            err[s] += e
            used[s] += m
        else:
            p, k = block64(ab, bb, f, h, symmetric)
            sums[s] += p if p == p else np.inf
            used[s] += k
        # exact: sum - err is below the exact partial sum
        if early_exit and sums[s] - err[s] >= tau * (used[s] + rest):
            alive[s] = False

    @inline
    def single(s, r, lo, hi, rest, like, det_addr, pa, pb, ranges, c, g, G, f, h,
               symmetric, tau, early_exit, sums, err, used, alive):
        """Block r = points lo:hi of pair s alone."""
        i = pa[s]
        j = pb[s]
        ab = points(like, det_addr[i], 2 * lo, 2 * (hi - lo))
        bb = points(like, det_addr[j], 2 * lo, 2 * (hi - lo))
        p = np.inf
        e = np.inf
        lo_a, hi_a = block_range(ab, ranges[i], r)
        lo_b, hi_b = block_range(bb, ranges[j], r)
        if lo_a <= hi_a and lo_b <= hi_b:  # no NaN or inf coordinate
            p, e = pair_bound(G[s], ranges[i, r], ranges[j, r], c[s],
                              block32(ab, bb, c[s], g[s], symmetric), h)
        settle(s, p, e, ab, bb, f, hi - lo, rest, h, symmetric, tau, early_exit, sums, err,
               used, alive)

    @plain
    def sums_kernel(like, det_addr, fs, fk, pa, pb, blocks, n, tau, early_exit,
                    symmetric, mixed):
        """(sums, used) of pairs s (detections pa[s], pb[s] under unit F fs[fk[s]]); detection
        d's 2n coordinates start at address det_addr[d] (arrays of like's dtype)."""
        S = pa.shape[0]
        D = det_addr.shape[0]
        h = 0.5 if symmetric else 1.0
        sums = np.zeros(S)
        used = np.zeros(S, dtype=np.int64)
        if not mixed:
            for s in range(S):
                sums[s], used[s] = pair64(points(like, det_addr[pa[s]], 0, 2 * n),
                                          points(like, det_addr[pb[s]], 0, 2 * n), fs[fk[s]],
                                          blocks, n, tau, early_exit, h, symmetric)
            return sums, used
        # once per detection: its centre, its block ranges (filled on first use)
        cen = np.empty((D, 2))
        for d in range(D):
            x = points(like, det_addr[d], 0, 2 * n)
            cen[d, 0], cen[d, 1] = centre(x, n)
        ranges = np.full((D, blocks.shape[0], 2), np.nan)
        # each pair's centred float32 F, then the blocks outermost: one block of every
        # detection of the frame (4 KB each) stays in cache while all its candidate pairs read
        # it, instead of each pair streaming whole detections from memory
        g = np.empty((S, 9), dtype=np.float32)
        G = np.empty((S, 3, 3))
        c = np.empty((S, 4), dtype=np.float32)
        for s in range(S):
            i = pa[s]
            j = pb[s]
            c[s, 0], c[s, 1], c[s, 2], c[s, 3] = cen[i, 0], cen[i, 1], cen[j, 0], cen[j, 1]
            centred_f(fs[fk[s]], cen[i, 0], cen[i, 1], cen[j, 0], cen[j, 1], g[s], G[s])
        # run_end[s]: end of s's run, the pairs of its a-side detection in its camera pair
        # (sorted together); their lines and weights in a are computed once, two pairs at a time
        run_end = np.empty(S, dtype=np.int64)
        for s in range(S - 1, -1, -1):
            same = s + 1 < S and pa[s + 1] == pa[s] and fk[s + 1] == fk[s]
            run_end[s] = run_end[s + 1] if same else s + 1
        err = np.zeros(S)
        alive = np.ones(S, dtype=np.bool_)  # not rejected early
        seen = 0
        for r in range(blocks.shape[0]):
            lo = blocks[r, 0]
            hi = blocks[r, 1]
            seen += hi - lo
            s = 0
            while s < S:
                first = -1  # an alive pair of the run waiting for a second one
                for t in range(s, run_end[s]):
                    if not alive[t]:
                        continue
                    if first < 0:
                        first = t
                        continue
                    i = pa[t]
                    ab = points(like, det_addr[i], 2 * lo, 2 * (hi - lo))
                    j = pb[first]
                    bb = points(like, det_addr[j], 2 * lo, 2 * (hi - lo))
                    j2 = pb[t]
                    db = points(like, det_addr[j2], 2 * lo, 2 * (hi - lo))
                    lo_a, hi_a = block_range(ab, ranges[i], r)
                    lo_b, hi_b = block_range(bb, ranges[j], r)
                    lo_d, hi_d = block_range(db, ranges[j2], r)
                    if lo_a <= hi_a and lo_b <= hi_b and lo_d <= hi_d:
                        one, two = block32x2(ab, bb, db, c[first, 0:2], c[first, 2:4],
                                             c[t, 2:4], g[first], g[t], symmetric)
                        p, e = pair_bound(G[first], ranges[i, r], ranges[j, r], c[first], one,
                                          h)
                        settle(first, p, e, ab, bb, fs[fk[first]], hi - lo, n - seen, h,
                               symmetric, tau, early_exit, sums, err, used, alive)
                        p, e = pair_bound(G[t], ranges[i, r], ranges[j2, r], c[t], two, h)
                        settle(t, p, e, ab, db, fs[fk[t]], hi - lo, n - seen, h,
                               symmetric, tau, early_exit, sums, err, used, alive)
                    else:
                        single(first, r, lo, hi, n - seen, like, det_addr, pa, pb,
                               ranges, c, g, G, fs[fk[first]], h, symmetric, tau, early_exit,
                               sums, err, used, alive)
                        single(t, r, lo, hi, n - seen, like, det_addr, pa, pb,
                               ranges, c, g, G, fs[fk[t]], h, symmetric, tau, early_exit,
                               sums, err, used, alive)
                    first = -1
                if first >= 0:
                    single(first, r, lo, hi, n - seen, like, det_addr, pa, pb, ranges,
                           c, g, G, fs[fk[first]], h, symmetric, tau, early_exit, sums, err,
                           used, alive)
                s = run_end[s]
        for s in range(S):
            total = sums[s]
            if alive[s] and not (total + err[s] < tau * used[s]) \
                    and not (total - err[s] >= tau * used[s]):
                # the bound does not settle the decision: float64 throughout
                sums[s], used[s] = pair64(points(like, det_addr[pa[s]], 0, 2 * n),
                                          points(like, det_addr[pb[s]], 0, 2 * n), fs[fk[s]],
                                          blocks, n, tau, early_exit, h, symmetric)
        return sums, used

    return sums_kernel


def screen_rows(x: np.ndarray, stride: int) -> PointRows | None:
    """The screening subset of (N,n,2) points as the kernel reads them: runs of SCREEN_RUN
    consecutive points, one run in every ``SCREEN_RUN * stride`` (1/stride of the points, the
    same fixed-topology ids in every detection). One contiguous copy per camera, shared by
    every camera pair; runs rather than single points so the copy reads 1/stride of the
    cache lines (every other point of a strided subset shares a line with a skipped one).
    None when the screen is off (stride 1) or would keep too few points to screen with."""
    x = np.asarray(x)
    N, n = int(x.shape[0]), int(x.shape[1])
    period = SCREEN_RUN * stride
    runs = n // period
    if stride <= 1 or runs * SCREEN_RUN < SCREEN_MIN_POINTS:
        return None
    picked = x[:, :runs * period].reshape(N, runs, period, 2)[:, :, :SCREEN_RUN]
    return point_rows(np.ascontiguousarray(picked).reshape(N, runs * SCREEN_RUN, 2))


#: consecutive points per screening run (8 float32 (u, v) = one 64-byte cache line)
SCREEN_RUN = 8
#: fewest screening points worth a screen (below this the full set is cheap anyway)
SCREEN_MIN_POINTS = 64


def screened_means(full: tuple[PointRows, PointRows], screen: tuple[PointRows, PointRows] | None,
                   F: np.ndarray, ia: np.ndarray, jb: np.ndarray, tau: float, margin: float,
                   symmetric: bool = True, early_exit: bool = True, backend: str = "auto",
                   precision: str = "mixed") -> tuple[np.ndarray, np.ndarray, int]:
    """The epipolar gate of detection pairs (ia[s] in a, jb[s] in b) of one camera pair:
    :func:`frame_screened_means` of that camera pair."""
    ia = np.asarray(ia)
    return frame_screened_means(dict(enumerate(full)),
                                None if screen is None else dict(enumerate(screen)),
                                {(0, 1): F}, np.zeros(ia.shape, np.int64), ia,
                                np.ones(ia.shape, np.int64), jb, tau, margin, symmetric,
                                early_exit, backend, precision)


def frame_screened_means(full: Mapping[int, PointRows], screen: Mapping[int, PointRows] | None,
                         F: Mapping[tuple[int, int], np.ndarray], cam_a: np.ndarray,
                         det_a: np.ndarray, cam_b: np.ndarray, det_b: np.ndarray, tau: float,
                         margin: float, symmetric: bool = True, early_exit: bool = True,
                         backend: str = "auto", precision: str = "mixed"
                         ) -> tuple[np.ndarray, np.ndarray, int]:
    """The epipolar gate of the detection pairs of a frame (as :func:`frame_sums`): (keep (S,)
    bool, mean (S,) px over the points the decision used, points evaluated); one kernel call
    for the screen and one for the full sets, every camera pair at once.

    Without a screen (None) every pair is decided on the full point sets (exact: the mean over
    all points both detections have, ``keep = mean < tau``). With one (screen[c]: the same
    fixed-topology subset of every camera's points, :func:`screen_rows`), each pair's mean is
    first taken over the subset; a pair whose subset mean is below ``tau - margin`` px is
    accepted with it, one at or above ``tau + margin`` is rejected, and the pairs in between
    (or with fewer than half of the subset's points present) are decided on the full sets. The
    subset mean of a regular subset of a dense mesh is within a small fraction of a px of the
    full mean (the vertices oversample the image), so the decisions are the full-set ones
    unless it errs by more than ``margin``.
    """
    kw = dict(symmetric=symmetric, early_exit=early_exit, backend=backend, precision=precision)
    pairs = [np.asarray(v) for v in (cam_a, det_a, cam_b, det_b)]
    S = pairs[0].size
    keep = np.zeros(S, dtype=bool)
    mean = np.full(S, np.nan)
    todo = np.arange(S)
    evaluated = 0
    if screen is not None and S:
        sums, used = frame_sums(screen, F, *pairs, tau + margin, **kw)
        evaluated += int(used.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            m = sums / used
        n = next(iter(screen.values())).n
        enough = used * 2 >= n
        rejected = enough & ~(sums < (tau + margin) * used)  # partial sums: early exit
        accepted = enough & ~rejected & (m < tau - margin)
        keep[accepted] = True
        mean[accepted] = m[accepted]
        todo = np.flatnonzero(~(accepted | rejected))
    if todo.size:
        sums, used = frame_sums(full, F, *(v[todo] for v in pairs), tau, **kw)
        evaluated += int(used.sum())
        ok = sums < tau * used
        keep[todo] = ok
        with np.errstate(invalid="ignore", divide="ignore"):
            mean[todo[ok]] = sums[ok] / used[ok]
    return keep, np.where(keep, mean, np.nan), evaluated
