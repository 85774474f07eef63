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
a frame in one call (:func:`frame_sums`: all camera pairs; each detection's block coordinate
ranges computed once), blocks outermost, so a detection's block stays in cache for its
candidate pairs (with several blocks the pairs are taken in an order that reads the same
detections close together: epipolar_kernel.locality_order), and the blocks the next pair
reads are prefetched while one pair's are summed (in chunks of the block, so reads and
arithmetic overlap). It
fuses everything per point (the line, both norms and the distance), and two pairs of one
detection in one camera pair run in one loop that computes that detection's lines and
weights once. By default (``precision "mixed"``) it runs
float32 SIMD (twice the lanes of float64) on the points as they are (no per-point centring:
4 of ~34 vector operations per 16 points) with a rigorous bound E of the block sum's rounding
error, from float32 unit roundoff u = 2^-24:

    E = (1 + 1e-3) [10 u B h sum w + 8 u h L sum |e| w^2 + (R + (m + 8) u) sum d]

(e the bilinear form of the points under F' = F (of unit norm) in float32 -- or, in the
second try below, of the points centred on each detection (u - c, integer c) under the float32
F' = T_b^T F T_a, where B scales with the detection's extent instead of its distance from the
image origin --, w = w_a + w_b and h = 1/2 (symmetric) or w = w_a and h = 1 (forward), w_a,
w_b the reciprocal line norms, B = [|u_b|,|v_b|,1] |F'| [|u_a|,|v_a|,1]^T from the block's
coordinate range, L = max(L_a, L_b) the same bound of the lines' first two coefficients;
terms: rounding of e, of the line norms (through their coefficients and the reciprocal square
root, within R = 2^-10 relative: x86's hardware estimate without a Newton step;
sum |e| (w_a^2 + w_b^2) <= sum |e| w^2), and of the block's m (<= BLOCK) float32 additions;
E does not depend on F' 's scale). A pair is rejected early when
``sum - E >= tau * (used + still to come)``, accepted when ``sum + E < tau * used``, rejected
when ``sum - E >= tau * used``; otherwise (the bound cannot settle it: its mean is within
~2^-10 of tau, a few pairs of a large-load frame) it is summed again in float32, centred and
with the refined 1/sqrt (R = 2^-20), and, if that cannot settle it either, in float64. Blocks
with a missing point or a point at (or very near) the epipole are summed in float64. So the
decisions are those of the float64 sums; an accepted pair's mean carries an error below
E / used (~1e-5 relative on full meshes in practice, the estimate's errors averaging over the
points; ``precision "float64"`` gives it to ~1e-13). The kernel reads each camera's points
where they are (:class:`PointRows`: a strided PointCloud2 field or a
contiguous array, float32 or float64; float64 points are summed in float64), without copies.
A point at the epipole has an undefined line: its distance is inf (or NaN, mapped to inf),
which rejects the pair.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from maem_ros.core.intsets import sorted_unique

#: points per contiguous block (SIMD-friendly, long enough that the per-block overhead stays
#: small and that a block's points stream from memory as one run: each doubling from 1024 to
#: 4096 made the large load's epipolar stage faster in alternating runs, 8192 no more; the
#: early exit is tested once per block, so longer blocks sum a little more of a rejected
#: pair); blocks are visited in a fixed shuffled order
BLOCK = 4096
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
    ``(flat[rows[i] + 2p], flat[rows[i] + 2p + 1])`` rectified px (NaN = missing), p = k when
    ``run`` is 0 (contiguous), else ``(k // run) * period + k % run`` (runs of ``run``
    consecutive points, one every ``period``: a screening subset read in place).

    flat: 1D C-contiguous float32/float64 (may span other message fields between rows, never
    read); rows (N,) int64 element offsets; n points per detection; ranges: None or, for
    points read contiguously (run 0), (N, blocks, 2) float32 each detection's (min, max)
    coordinate over each of its BLOCK-point blocks in their natural order, (inf, -inf) where
    one is NaN (made by a decoder's pass, :func:`screen_copies`; the kernel's error bound
    trusts them).
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

    def contiguous(self) -> "PointRows":
        """The same points, each detection's n points contiguous (a copy when read in runs)."""
        return self if not self.run else point_rows(self._gather(self.rows))

    def points(self, i: int) -> np.ndarray:
        """(n,2) copy of detection i's points."""
        return self._gather(self.rows[i:i + 1])[0]

    def _gather(self, rows: np.ndarray) -> np.ndarray:
        """(len(rows),n,2) copy of the points of the detections at element offsets rows."""
        at = rows[:, None] + 2 * self.positions(np.arange(self.n))[None, :]
        return np.stack([self.flat[at], self.flat[at + 1]], axis=-1)


def point_rows(x: np.ndarray | PointRows, ranges: np.ndarray | None = None) -> PointRows:
    """(N,n,2) points -> :class:`PointRows`, zero-copy when each detection's (n,2) block is
    contiguous and aligned (a contiguous array, or a field view of a PointCloud2 with one
    detection per point); otherwise one contiguous float64 copy. ranges: the block ranges
    of x's float32 points made by :func:`screen_copies` (PointRows.ranges), or None."""
    if isinstance(x, PointRows):
        return x
    x = np.asarray(x)
    if x.ndim != 3 or x.shape[2] != 2:
        raise ValueError(f"epipolar points: expected (N,n,2), got {x.shape}")
    N, n = int(x.shape[0]), int(x.shape[1])
    if ranges is not None:
        if ranges.shape != (N, -(-n // BLOCK), 2) or x.dtype != np.float32:
            raise ValueError(f"epipolar points: block ranges {ranges.shape} do not describe "
                             f"{x.dtype} points {x.shape}")
        rows = point_rows(x)  # not dataclasses.replace: its overhead, ~50 calls a frame set
        return PointRows(rows.flat, rows.rows, rows.n, rows.run, rows.period, ranges)
    if x.dtype not in (np.float32, np.float64) or not x.dtype.isnative:
        x = x.astype(np.float64)
    if N and n and x.flags.c_contiguous and x.flags.aligned:
        # the common case as a plain view (as_strided and ctypes cost more per call)
        flat = x.reshape(-1).view()
        flat.flags.writeable = False
        return PointRows(flat, np.arange(N, dtype=np.int64) * (2 * n), n)
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
            raise ValueError(f"epipolar pairs: no fundamental matrix for camera pair "
                             f"{(int(cam_a[s]), int(cam_b[s]))}")
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
               F: Mapping[tuple[int, int], np.ndarray] | PairMatrices, cam_a: np.ndarray,
               det_a: np.ndarray, cam_b: np.ndarray, det_b: np.ndarray, tau: float,
               symmetric: bool = True,
               early_exit: bool = True, backend: str = "auto", precision: str = "mixed",
               count_rest: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Distance sums of the detection pairs of every camera pair of a frame, in one kernel call.

    points[c]: camera c's (N,n,2) rectified px (float32 or float64, point k = same body spot,
    NaN = missing) or :class:`PointRows` (read in place); F[(a, b)] (3,3) with
    ``x_b^T F x_a = 0``; pair s is detection det_a[s] of camera cam_a[s] against det_b[s] of
    camera cam_b[s]. Returns (sums (S,) px, used (S,) int points summed). Reject a pair iff
    ``sums >= tau * used`` (identical with or without early exit). An accepted pair's sum is
    complete (sum / used = its mean distance); with early exit a rejected pair's sum and count
    are partial.

    precision (numba backend, float32 points): ``mixed`` sums float32 SIMD distances with a
    rigorous bound of their rounding error and re-runs any pair whose decision the bound
    cannot settle (in float32 with a refined 1/sqrt, then in float64), so the decisions are
    the float64 ones; an accepted pair's sum is then
    within its bound (~1e-5 relative in practice) of the exact one. ``float64``: every distance
    in float64 (sums to ~1e-13).

    count_rest: with early exit, a rejected pair's ``used`` also counts the points its sum did
    not reach (read for presence only), so ``used`` is every point both detections have, for
    every pair, and early exit changes only the rejected pairs' sums.
    """
    sums, used, _ = _frame_sums(points, F, cam_a, det_a, cam_b, det_b, tau, symmetric,
                                early_exit, backend, precision, count_rest)
    return sums, used


def _frame_sums(points: Mapping[int, np.ndarray | PointRows],
                F: Mapping[tuple[int, int], np.ndarray] | PairMatrices, cam_a: np.ndarray,
                det_a: np.ndarray, cam_b: np.ndarray, det_b: np.ndarray, tau: float,
                symmetric: bool,
                early_exit: bool, backend: str, precision: str, count_rest: bool
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`frame_sums` and, third, the points each pair's sum reached (``used`` without
    count_rest)."""
    plan = _frame_pairs(points, F, cam_a, det_a, cam_b, det_b)
    return _level_sums(plan, points, np.arange(plan.which.size), tau, symmetric, early_exit,
                       backend, precision, count_rest)


@dataclass(frozen=True)
class _FramePairs:
    """The detection pairs of a frame, checked and prepared once for every level of
    :func:`frame_screened_means`: each side's detection as a frame-wide key (``offsets`` of
    the cameras ``cams`` plus the index), each pair's row ``which`` of ``unit`` (its unit F),
    and the kernel's pair order over all of them (``order``: by a-side detection, camera pair,
    b-side detection; stable). A level's pairs take that order filtered to them, the order a
    sort of the level's pairs alone gives."""

    cam_a: np.ndarray
    det_a: np.ndarray
    cam_b: np.ndarray
    det_b: np.ndarray
    cams: list[int]
    counts: np.ndarray
    offsets: np.ndarray
    key_a: np.ndarray
    key_b: np.ndarray
    which: np.ndarray
    unit: np.ndarray
    order: np.ndarray


def _frame_pairs(points: Mapping[int, np.ndarray | PointRows],
                 F: Mapping[tuple[int, int], np.ndarray] | PairMatrices, cam_a: np.ndarray,
                 det_a: np.ndarray, cam_b: np.ndarray, det_b: np.ndarray) -> _FramePairs:
    """:class:`_FramePairs` of pairs (det_a[s] of camera cam_a[s], det_b[s] of cam_b[s]) over
    the cameras' points; ValueError naming the first bad input."""
    pairs = [np.ascontiguousarray(v, dtype=np.int64) for v in (cam_a, det_a, cam_b, det_b)]
    if any(v.ndim != 1 or v.shape != pairs[0].shape for v in pairs):
        raise ValueError(f"epipolar pairs: cameras and detections must be equal-length 1D, got "
                         f"{[v.shape for v in pairs]}")
    cam_a, det_a, cam_b, det_b = pairs
    cams = sorted_unique(np.concatenate([cam_a, cam_b])).tolist()
    if cams and cams[0] < 0:
        raise ValueError(f"epipolar pairs: camera indices must be >= 0, got {cams[0]}")
    missing = [c for c in cams if c not in points]
    if missing:
        raise ValueError(f"epipolar pairs: no points for camera(s) {missing}")
    counts = np.array([point_rows(points[c]).count for c in cams], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    keys = []
    for cam, det in ((cam_a, det_a), (cam_b, det_b)):
        slot = np.searchsorted(cams, cam)
        if det.size and (det.min() < 0 or np.any(det >= counts[slot])):
            # the kernel runs without bounds checks
            raise ValueError("epipolar pairs: detection index out of range")
        keys.append(offsets[slot] + det)
    Fs = pair_matrices(F)
    which = Fs.rows(cam_a, cam_b)
    W = int(which.max()) + 1 if which.size else 1
    K = int(offsets[-1])
    # one stable sort on a combined key (np.lexsort of the three keys took 3x as long)
    order = np.argsort((keys[0] * W + which) * K + keys[1], kind="stable")
    return _FramePairs(cam_a, det_a, cam_b, det_b, cams, counts, offsets, keys[0], keys[1],
                       which, Fs.unit, order)


def _level_sums(plan: _FramePairs, points: Mapping[int, np.ndarray | PointRows],
                todo: np.ndarray, tau: float, symmetric: bool, early_exit: bool, backend: str,
                precision: str, count_rest: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(sums, used, points summed) of the plan's pairs ``todo`` (indices, ascending) over
    ``points`` (the plan's cameras, the same detections: the full sets or one screening
    level's subsets), as :func:`_frame_sums`."""
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision: expected one of {PRECISIONS}, got {precision!r}")
    cams = plan.cams
    rows = {c: point_rows(points[c]) for c in cams}
    if len({(r.run, r.period) for r in rows.values()}) > 1:  # one layout per kernel call
        rows = {c: r.contiguous() for c, r in rows.items()}
    sizes = {rows[c].n for c in cams}
    if len(sizes) > 1:
        raise ValueError(f"epipolar points: expected (N,n,2) with one n for every camera, got "
                         f"n={sorted(sizes)}")
    if any(rows[c].count != k for c, k in zip(cams, plan.counts.tolist())):
        raise ValueError("epipolar points: a level's detections differ from the pairs' cameras'")
    n = sizes.pop() if sizes else 0
    S = todo.size
    if S == 0 or n == 0:
        return np.zeros(S), np.zeros(S, dtype=np.int64), np.zeros(S, dtype=np.int64)
    use_numba = backend == "numba" or (backend == "auto" and _numba is not None)
    if not use_numba:
        return _numpy_level_sums(plan, rows, todo, float(tau) if early_exit else np.inf,
                                 bool(symmetric), bool(count_rest))
    if _numba is None:
        raise ValueError("backend: 'numba' requested but numba is not installed")
    return _numba_level_sums(rows, plan, todo, n, float(tau), bool(symmetric),
                             bool(early_exit), precision, bool(count_rest))


def _numpy_level_sums(plan: _FramePairs, rows: dict[int, PointRows], todo: np.ndarray,
                      tau: float, symmetric: bool, count_rest: bool
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numpy reference on the plan's pairs todo, one camera pair at a time."""
    S = todo.size
    which = plan.which[todo]
    cam_a, det_a, cam_b, det_b = (v[todo] for v in (plan.cam_a, plan.det_a, plan.cam_b,
                                                    plan.det_b))
    out = np.zeros(S), np.zeros(S, dtype=np.int64), np.zeros(S, dtype=np.int64)
    for g in sorted_unique(which).tolist():
        s = np.flatnonzero(which == g)
        for v, got in zip(out, _numpy_sums(rows[int(cam_a[s[0]])], rows[int(cam_b[s[0]])],
                                           plan.unit[g].reshape(3, 3), det_a[s], det_b[s],
                                           tau, symmetric, count_rest)):
            v[s] = got
    return out


def _numba_level_sums(rows: dict[int, PointRows], plan: _FramePairs, todo: np.ndarray, n: int,
                      tau: float, symmetric: bool, early_exit: bool, precision: str,
                      count_rest: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numba kernel on the plan's pairs todo: the detections they read numbered once
    (each one's block ranges computed once for all its pairs), the pairs in the
    plan's order (a detection's pairs one after another: its block stays hot; those of one
    camera pair together: they share its lines; the kernel reorders these runs when there are
    several blocks)."""
    cams = plan.cams
    flats = [rows[c].flat for c in cams]
    if len({f.dtype for f in flats}) > 1:  # mixed float32/float64 cameras: all in float64
        flats = [f.astype(np.float64) for f in flats]
    # float64 points (keypoints: few per detection) always take the float64 path
    mixed = (precision == "mixed" and flats[0].dtype == np.float32 and _rsqrt_within_bound())
    chosen = np.zeros(plan.which.size, bool)
    chosen[todo] = True
    order = plan.order[chosen[plan.order]]  # this level's pairs in the kernel's order
    key_a, key_b = plan.key_a[order], plan.key_b[order]
    # flats stay referenced during the call
    dets, rank, det_addr = _detections_read(plan, key_a, key_b, flats,
                                            [rows[c].rows for c in cams])
    like = flats[0]
    layout = rows[cams[0]]
    ranges = _known_ranges([rows[c] for c in cams], dets, n, mixed)
    if layout.run:  # a subset read in runs: each detection's points gathered once, contiguous
        like = _gather_buffer(dets.size * 2 * n, like.dtype).reshape(dets.size, 2 * n)
        _numba_kernels().gather_runs(flats[0], det_addr, layout.run, layout.period, like, 0,
                                     np.empty((0, 0), like.dtype))
        det_addr = like.ctypes.data + np.arange(dets.size, dtype=np.int64) * like.strides[0]
        like = like.reshape(-1)
    if like.flags.writeable:
        # one compiled kernel per dtype: a writable array would take another, compiled (and
        # cached) apart with its own inlining, so sums could differ in the last bits between
        # points read in place (read-only views) and gathered ones
        like = like.view()
        like.setflags(write=False)
    got = _numba_kernels().sums_kernel(
        like, det_addr, ranges, plan.unit, plan.which[order], rank[key_a], rank[key_b],
        block_order(n), n, tau, early_exit, symmetric, mixed,
        mixed and _refined_rsqrt_within_bound(), count_rest)
    # back from the kernel's order to todo's
    at = np.empty(plan.which.size, np.int64)
    at[todo] = np.arange(todo.size)
    out = np.empty(todo.size), np.empty(todo.size, dtype=np.int64), np.empty(todo.size, np.int64)
    for v, g in zip(out, got):
        v[at[order]] = g
    return out


def _detections_read(plan: _FramePairs, key_a: np.ndarray, key_b: np.ndarray,
                     flats: list[np.ndarray], rows: list[np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(dets, rank, det_addr) of the detections that pairs (frame-wide keys key_a[s],
    key_b[s]) read: their keys ascending, each key's place among them (rank[key]; meaningless
    for keys no pair reads) and each one's first coordinate as an address in flats (one
    array per camera of the plan, of one dtype; rows: the cameras' PointRows.rows)."""
    present = np.zeros(int(plan.offsets[-1]), bool)
    present[key_a] = True
    present[key_b] = True
    dets = np.flatnonzero(present)
    rank = np.cumsum(present) - 1
    det_slot = np.searchsorted(plan.offsets, dets, side="right") - 1
    det_row = np.concatenate(rows)[dets]
    base = np.array([f.__array_interface__["data"][0] for f in flats], dtype=np.int64)
    return dets, rank, base[det_slot] + det_row * flats[0].dtype.itemsize


def _known_ranges(rows: list[PointRows], dets: np.ndarray, n: int, mixed: bool) -> np.ndarray:
    """(D, blocks, 2) float64: the block ranges of the detections dets (frame-wide keys over
    the cameras' rows) in the kernel's block order (:func:`block_order`), NaN where a
    camera's were not given (the kernel computes them when it first reads a block). A
    decoder's ranges spare the kernel a pass over the points (most of it at the full-mesh
    level, whose points come from memory)."""
    order = block_order(n)
    given = [r.ranges for r in rows]
    if not mixed or all(g is None for g in given):
        return np.full((dets.size, order.shape[0], 2), np.nan)
    natural = np.concatenate([g if g is not None else
                              np.full((r.count, order.shape[0], 2), np.nan, np.float32)
                              for g, r in zip(given, rows)])
    return natural[dets][:, order[:, 0] // BLOCK].astype(np.float64)


#: per thread, the bytes the screens' gathered points are written to, kept from call to call
_scratch = threading.local()


def _gather_buffer(size: int, dtype: np.dtype, slot: int = 0, align: int = 64) -> np.ndarray:
    """(size,) ``dtype`` starting on an ``align``-byte boundary, in this thread's scratch
    memory ``slot`` (valid until the next call for that slot in this thread). Kept, not
    allocated per call: a fresh 7 MB buffer (the large load's 1/8 screen) came from new pages
    now and then, and their first writes page-faulted (hundreds of faults: an outlier frame),
    while memory reused from the previous frame is already mapped. Grown with
    headroom (frame sets vary in size), as each growth faults its new pages once."""
    need = size * np.dtype(dtype).itemsize + align
    if not hasattr(_scratch, "raw"):
        _scratch.raw = {}
    raw = _scratch.raw.get(slot)
    if raw is None or raw.size < need:
        raw = _scratch.raw[slot] = np.empty(max(need + need // 2, 2 * raw.size
                                                if raw is not None else 0), np.uint8)
    skip = -raw.ctypes.data % align
    return raw[skip:skip + need - align].view(dtype)


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
        screen = screen_rows(x, 2)
        epipolar_sums(screen, screen, F, one, one, 1.0, True, True, "numba", "mixed")
    screen_copies(np.ones((1, BLOCK, 2), dtype=np.float32), (2, 4))


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
                tau: float, symmetric: bool, count_rest: bool
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference path: all pairs of a block at once, blocks in the fixed order, early exit;
    (sums, used, points summed)."""
    S = ia.size
    sums = np.zeros(S)
    summed = np.zeros(S, dtype=np.int64)
    rest = np.zeros(S, dtype=np.int64)  # count_rest: present points after a pair's exit
    seen = 0
    alive = np.arange(S)
    dead = np.arange(0)
    for idx in _block_indices(ra.n):
        if count_rest and dead.size:
            rest[dead] += _block_points(ra, rb, ia[dead], jb[dead], idx, F, symmetric)[1].sum(1)
        if alive.size == 0:
            if not (count_rest and dead.size):
                break
            continue
        d, present = _block_points(ra, rb, ia[alive], jb[alive], idx, F, symmetric)
        sums[alive] += np.where(present, d, 0.0).sum(axis=1)
        summed[alive] += present.sum(axis=1)
        seen += idx.size
        # used + (points still to come) bounds the final count from above
        with np.errstate(invalid="ignore"):  # inf * 0 without early exit: NaN, not < anything
            go_on = sums[alive] < tau * (summed[alive] + (ra.n - seen))
        dead = np.concatenate([dead, alive[~go_on]])
        alive = alive[go_on]
    return sums, summed + rest, summed


def _block_points(ra: PointRows, rb: PointRows, ia: np.ndarray, jb: np.ndarray,
                  idx: np.ndarray, F: np.ndarray, symmetric: bool
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(distances (S,m) px, present (S,m) bool) of points idx of the pairs (ia, jb)."""
    oa = ra.rows[ia, None] + 2 * ra.positions(idx)[None, :]
    ob = rb.rows[jb, None] + 2 * rb.positions(idx)[None, :]
    A = np.stack([ra.flat[oa], ra.flat[oa + 1]], axis=-1)
    B = np.stack([rb.flat[ob], rb.flat[ob + 1]], axis=-1)
    d = point_distances(A, B, F, symmetric)
    return d, ~np.isnan(d)


#: float32 unit roundoff
_U32 = 2.0 ** -24
#: relative error bound of the float32 1/sqrt of the kernels: the hardware estimate alone on
#: x86-64 (documented |rel err| <= 1.5 * 2^-12, 3.7e-4; rsqrt14ps 2^-14; 2^-10 leaves a margin
#: of ~2.7), elsewhere the estimate with LLVM's Newton steps. Checked at first use
#: (:func:`_rsqrt_within_bound`)
_RSQRT_ERR = 2.0 ** -10
#: the same of the refined float32 1/sqrt that a pair's second try takes (the estimate plus
#: one Newton step in float32: ~3 * 2^-24 + 1.7 * 2^-24; 2^-20 leaves a margin of ~3)
_RSQRT_ERR_REFINED = 2.0 ** -20
#: relative slack on the error bound for its own (second-order) rounding
_BOUND_SLACK = 1e-3
#: float32 bit patterns mapped to ordered int32 keys: keys of -inf and +inf (finite in between)
_KEY_NEG_INF = -2139095041
_KEY_POS_INF = 2139095040


@lru_cache(maxsize=1)
def _rsqrt_within_bound() -> bool:
    """Whether the compiled float32 1/sqrt of the kernels (the instructions LLVM picks for
    this CPU) is within half of _RSQRT_ERR of the exact value; if not, the mixed kernel's
    error bound would not hold, and "mixed" runs in float64 instead."""
    from maem_ros.core.association.gates.epipolar_kernel import rsqrt32
    return _rsqrt_probe(rsqrt32) <= _RSQRT_ERR / 2


@lru_cache(maxsize=1)
def _refined_rsqrt_within_bound() -> bool:
    """Whether the refined float32 1/sqrt of a pair's second try is within half of
    _RSQRT_ERR_REFINED; if not, pairs the first bound cannot settle go to float64 at once."""
    from maem_ros.core.association.gates.epipolar_kernel import rsqrt32_refined
    return _rsqrt_probe(rsqrt32_refined) <= _RSQRT_ERR_REFINED / 2


def _rsqrt_probe(kernel) -> float:
    """Largest relative error of a compiled float32 1/sqrt ``kernel(q, out, step)``. An
    estimate depends on the mantissa and the exponent's parity: every 61st float32 in [1, 4)
    (8 or more arguments in every table cell of the 12- and 14-bit estimates) through the
    widest vector loop and through the narrower remainder code (chunks shorter than one
    vector), and a sweep over the whole exponent range."""
    every = np.arange(np.float32(1.0).view(np.int32), np.float32(4.0).view(np.int32),
                      61, dtype=np.int32).view(np.float32)
    q = np.concatenate([every, np.geomspace(1e-30, 1e30, 200_003).astype(np.float32)])
    worst = 0.0
    for probe, step in ((q, q.size), (every, _REMAINDER_PROBE)):
        got = np.empty_like(probe)
        kernel(probe, got, step)
        exact = 1.0 / np.sqrt(probe.astype(np.float64))
        worst = max(worst, float(np.max(np.abs(got / exact - 1.0))))
    return worst


#: arguments per chunk of the remainder probe: fewer than a 512-bit vector of float32 lanes
_REMAINDER_PROBE = 15


@lru_cache(maxsize=1)
def _numba_kernels():
    """The numba kernels' module (compiled, or loaded from numba's on-disk cache, on first
    use)."""
    from maem_ros.core.association.gates import epipolar_kernel
    return epipolar_kernel


def screen_rows(x: np.ndarray | PointRows, stride: int) -> PointRows | None:
    """The screening subset of (N,n,2) points (or their full-set :class:`PointRows`) as the
    kernel reads them: runs of SCREEN_RUN consecutive points, one run in every
    ``SCREEN_RUN * stride`` (1/stride of the points, the same fixed-topology ids in every
    detection), described over x's own memory (no copy here; the numba backend gathers the
    runs of the detections that take part once per call). Runs rather than single points so
    a screen reads 1/stride of the cache lines (every other point of a strided subset shares
    a line with a skipped one). None when the screen is off (stride 1) or would keep too few
    points to screen with."""
    full = point_rows(x)
    if full.run:
        raise ValueError("screen_rows: expected the full point set, got a subset")
    period = SCREEN_RUN * stride
    runs = full.n // period
    if stride <= 1 or runs * SCREEN_RUN < SCREEN_MIN_POINTS:
        return None
    return PointRows(full.flat, full.rows, runs * SCREEN_RUN, SCREEN_RUN, period)


class ScreenCopies(NamedTuple):
    """What a decoder's pass over one camera's (N,n,2) float32 points leaves for the mesh
    gate (:func:`screen_copies`)."""

    #: {stride: (N,m,2) float32 read-only}: each screening subset, contiguous
    copies: dict[int, np.ndarray]
    #: {stride: (N, blocks, 2) float32 read-only}: PointRows.ranges of the full set
    #: (stride 1) and of each copy made in the one pass (empty without numba)
    block_ranges: dict[int, np.ndarray]
    #: the first detection with an infinite coordinate (-1: none; NaN = missing is allowed)
    first_inf: int


def screen_copies(x: np.ndarray, strides: Sequence[int]) -> ScreenCopies:
    """The screening subsets of one camera's (N,n,2) float32 points for each of ``strides``
    (:func:`screen_rows`) copied contiguous (strides whose screen is off left out), the full
    set's and the copies' block ranges, and the first detection with an infinite coordinate.

    For a decoder, whose finiteness check reads every point anyway: with numba, one pass
    scans each detection (its block ranges are the finiteness check) and copies its runs (of
    the finest subset and of one coarser subset nested in it) while they are in cache. The
    gate then reads the copies where it would gather the same runs from scattered cache
    lines when the frame set is complete (on maem-bench --load large the gate loses more
    gather time than decoding gains, and decoding happens while the other cameras' messages
    are still arriving), and the ranges where its kernel would scan the points again
    (:func:`_known_ranges`)."""
    x = np.asarray(x, dtype=np.float32)
    full = point_rows(x)
    levels = [(s, screen_rows(full, s)) for s in sorted(set(int(v) for v in strides))]
    levels = [(s, rows) for s, rows in levels if rows is not None]  # finest first
    if _numba is None or full.count == 0 or not levels:
        bad = np.flatnonzero(np.isinf(x).any(axis=(1, 2)))
        copies = {s: rows._gather(rows.rows) for s, rows in levels}
        return ScreenCopies(_read_only(copies), {}, int(bad[0]) if bad.size else -1)
    (stride, fine), rest = levels[0], levels[1:]
    nested = [(s, rows) for s, rows in rest if rows.period % fine.period == 0]
    coarse_stride, coarse = nested[0] if nested else (0, None)
    out = np.empty((full.count, 2 * fine.n), np.float32)
    every = coarse.period // fine.period if coarse is not None else 0
    inner = np.empty((full.count, 2 * coarse.n) if coarse is not None else (0, 0), np.float32)
    ranges = {1: _ranges_buffer(full.count, full.n), stride: _ranges_buffer(full.count, fine.n)}
    inner_ranges = _ranges_buffer(full.count, coarse.n if coarse is not None else 0)
    det_addr = full.flat.__array_interface__["data"][0] + full.rows * full.flat.itemsize
    first_inf = _numba_kernels().scan_gather_runs(
        full.flat, det_addr, full.n, BLOCK, fine.run, fine.period, out, every, inner, ranges[1],
        ranges[stride], inner_ranges)
    copies = {stride: out.reshape(full.count, fine.n, 2)}
    if coarse is not None:
        copies[coarse_stride] = inner.reshape(full.count, coarse.n, 2)
        ranges[coarse_stride] = inner_ranges
    for s, rows in rest:  # a level not nested in the finest one: gathered on its own
        if s not in copies:
            copies[s] = rows._gather(rows.rows)
    return ScreenCopies(_read_only(copies), _read_only(ranges), int(first_inf))


def _ranges_buffer(count: int, n: int) -> np.ndarray:
    """(count, blocks of n points, 2) float32 for PointRows.ranges."""
    return np.empty((count, -(-n // BLOCK), 2), np.float32)


def _read_only(arrays: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    for a in arrays.values():
        a.setflags(write=False)
    return arrays


#: consecutive points per screening run (8 float32 (u, v) = one 64-byte cache line)
SCREEN_RUN = 8
#: fewest screening points worth a screen (below this the full set is cheap anyway)
SCREEN_MIN_POINTS = 64


def _gathered_screens(plan: _FramePairs, screens: Sequence[ScreenLevel], backend: str
                      ) -> Sequence[ScreenLevel]:
    """The screening levels with the subsets of the plan's detections gathered once,
    contiguous, for the numba kernel: one pass over each detection's points copies the finest
    level's runs and, of them, a coarser level's (its runs are every k-th of the finest's when
    its period is a multiple of the finest's). The coarse level's own gather, a second pass
    over scattered cache lines, cost more than the copies add to the screen's pass (which
    reads those cache lines anyway). The levels as they are where that does not
    apply (the numpy backend reads the runs in place; other layouts are gathered level by
    level in the kernel call)."""
    if not screens or len(screens) > 2 or backend == "numpy" or _numba is None:
        return screens
    levels = [{c: point_rows(level[c]) for c in plan.cams} for level, _ in screens]
    fine = levels[-1]
    rows = [fine[c] for c in plan.cams]
    every = 0
    if len(levels) == 2:
        coarse = levels[0]
        if any(coarse[c].flat is not fine[c].flat or coarse[c].rows is not fine[c].rows
               or coarse[c].run != fine[c].run or coarse[c].period % fine[c].period
               for c in plan.cams):
            return screens
        every = coarse[plan.cams[0]].period // fine[plan.cams[0]].period
        if any(coarse[c].period != every * fine[c].period for c in plan.cams):
            return screens
    if len({(r.run, r.period, r.n, r.flat.dtype) for r in rows}) > 1 or not rows[0].run:
        return screens
    # flats keeps the message buffers referenced while the kernel reads them by address;
    # slot: each detection's place among those gathered
    flats = [r.flat for r in rows]
    dets, slot, det_addr = _detections_read(plan, plan.key_a, plan.key_b, flats,
                                            [r.rows for r in rows])
    run, period, n, dtype = rows[0].run, rows[0].period, rows[0].n, rows[0].flat.dtype
    out = _gather_buffer(dets.size * 2 * n, dtype, 1).reshape(dets.size, 2 * n)
    n_coarse = levels[0][plan.cams[0]].n if every else 0
    coarse = _gather_buffer(dets.size * 2 * n_coarse, dtype, 2).reshape(dets.size, 2 * n_coarse)
    _numba_kernels().gather_runs(flats[0], det_addr, run, period, out, every, coarse)
    gathered = []
    for (level, margin), buffer, size in zip(screens, [coarse, out][-len(screens):],
                                             [n_coarse, n][-len(screens):]):
        flat = buffer.reshape(-1).view()
        flat.setflags(write=False)
        at = slot.clip(0) * (2 * size)  # each detection's row in the buffer (unread if absent)
        gathered.append(({c: PointRows(flat, at[plan.offsets[k]:plan.offsets[k + 1]], size)
                          for k, c in enumerate(plan.cams)}, margin))
    return gathered


#: one screening level: the subset of every camera's points (:func:`screen_rows`) and its margin
#: (px): subset means within it of tau go on to the next level
ScreenLevel = tuple[Mapping[int, PointRows], float]


def screened_means(full: tuple[PointRows, PointRows], screen: tuple[PointRows, PointRows] | None,
                   F: np.ndarray, ia: np.ndarray, jb: np.ndarray, tau: float, margin: float,
                   symmetric: bool = True, early_exit: bool = True, backend: str = "auto",
                   precision: str = "mixed") -> tuple[np.ndarray, np.ndarray, int]:
    """The epipolar gate of detection pairs (ia[s] in a, jb[s] in b) of one camera pair with
    one screening level (or None): :func:`frame_screened_means` of that camera pair."""
    ia = np.asarray(ia)
    return frame_screened_means(dict(enumerate(full)),
                                [] if screen is None else [(dict(enumerate(screen)), margin)],
                                {(0, 1): F}, np.zeros(ia.shape, np.int64), ia,
                                np.ones(ia.shape, np.int64), jb, tau, symmetric, early_exit,
                                backend, precision)


def frame_screened_means(full: Mapping[int, PointRows], screens: Sequence[ScreenLevel],
                         F: Mapping[tuple[int, int], np.ndarray] | PairMatrices,
                         cam_a: np.ndarray, det_a: np.ndarray, cam_b: np.ndarray,
                         det_b: np.ndarray, tau: float,
                         symmetric: bool = True, early_exit: bool = True,
                         backend: str = "auto", precision: str = "mixed"
                         ) -> tuple[np.ndarray, np.ndarray, int]:
    """The epipolar gate of the detection pairs of a frame (as :func:`frame_sums`): (keep (S,)
    bool, mean (S,) px over the points the decision used, points evaluated); one kernel call
    per level for every camera pair at once.

    Without screening levels (empty) every pair is decided on the full point sets (exact: the
    mean over all points both detections have, ``keep = mean < tau``). With them (coarse to
    fine; each the same fixed-topology subset of every camera's points and a margin), the
    pairs still open are taken over each level's subset in turn: a pair whose subset mean is
    below ``tau - margin`` px is accepted with it, one at or above ``tau + margin`` is
    rejected, and the rest (or those with fewer than half of the subset's points present) go
    on to the next level, the last to the full sets. The subset mean of a regular subset of a
    dense mesh is within a small fraction of the full mean (the vertices oversample the
    image; the error grows with the mean and with the stride), so the decisions are the
    full-set ones unless a level errs by more than its margin.
    """
    plan = _frame_pairs(full, F, cam_a, det_a, cam_b, det_b)  # once for every level
    screens = _gathered_screens(plan, screens, backend)
    S = plan.which.size
    keep = np.zeros(S, dtype=bool)
    mean = np.full(S, np.nan)
    todo = np.arange(S)
    evaluated = 0
    for screen, margin in screens:
        if not todo.size:
            break
        # every point counted: whether half the subset is there does not depend on where an
        # early exit stopped
        sums, used, summed = _level_sums(plan, screen, todo, tau + margin, symmetric,
                                         early_exit, backend, precision, True)
        evaluated += int(summed.sum())
        with np.errstate(invalid="ignore", divide="ignore"):
            m = sums / used
        n = next(iter(screen.values())).n
        enough = used * 2 >= n
        rejected = enough & ~(sums < (tau + margin) * used)  # partial sums: early exit
        accepted = enough & ~rejected & (m < tau - margin)
        keep[todo[accepted]] = True
        mean[todo[accepted]] = m[accepted]
        todo = todo[~(accepted | rejected)]
    if todo.size:
        sums, used, _ = _level_sums(plan, full, todo, tau, symmetric, early_exit, backend,
                                    precision, False)
        evaluated += int(used.sum())
        ok = sums < tau * used
        keep[todo] = ok
        with np.errstate(invalid="ignore", divide="ignore"):
            mean[todo[ok]] = sums[ok] / used[ok]
    return keep, np.where(keep, mean, np.nan), evaluated
