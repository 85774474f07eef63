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
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from maem_ros.core.association.gates.epipolar_constants import (
    BACKENDS,
    BLOCK,
    EPIPOLE_NORM,
    PRECISIONS,
)
from maem_ros.core.association.gates.point_rows import (
    PairMatrices,
    PointRows,
    block_indices,
    block_order,
    pair_matrices,
    point_rows,
)
from maem_ros.core.association.gates.rsqrt_check import refined_rsqrt_within_bound, rsqrt_within_bound
from maem_ros.core.detections import vertex_subset
from maem_ros.core.intsets import sorted_unique
from maem_ros.core.jit import have_numba

__all__ = [
    "BACKENDS",
    "PRECISIONS",
    "PairMatrices",
    "PointRows",
    "block_order",
    "epipolar_sums",
    "frame_sums",
    "pair_matrices",
    "point_distances",
    "point_rows",
    "vertex_subset",
    "warmup",
]


def epipolar_sums(
    xa: np.ndarray | PointRows,
    xb: np.ndarray | PointRows,
    F: np.ndarray,
    ia: np.ndarray,
    jb: np.ndarray,
    tau: float,
    symmetric: bool = True,
    early_exit: bool = True,
    backend: str = "auto",
    precision: str = "mixed",
) -> tuple[np.ndarray, np.ndarray]:
    """Distance sums of the detection pairs (ia[s] in a, jb[s] in b) of one camera pair.

    xa (Na,n,2), xb (Nb,n,2) rectified px (float32 or float64, point k = same body spot, NaN =
    missing) or their :class:`PointRows`; F (3,3) a->b; ia, jb (S,) int detection indices.
    Returns (sums (S,) px, used (S,) int points summed): :func:`frame_sums` of one camera pair.
    """
    ia = np.asarray(ia)
    return frame_sums(
        {0: point_rows(xa), 1: point_rows(xb)},
        {(0, 1): F},
        np.zeros(ia.shape, np.int64),
        ia,
        np.ones(ia.shape, np.int64),
        jb,
        tau,
        symmetric,
        early_exit,
        backend,
        precision,
    )


def frame_sums(
    points: Mapping[int, np.ndarray | PointRows],
    F: Mapping[tuple[int, int], np.ndarray] | PairMatrices,
    cam_a: np.ndarray,
    det_a: np.ndarray,
    cam_b: np.ndarray,
    det_b: np.ndarray,
    tau: float,
    symmetric: bool = True,
    early_exit: bool = True,
    backend: str = "auto",
    precision: str = "mixed",
    count_rest: bool = False,
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
    rigorous bound of their rounding error and re-runs any pair whose decision the bound
    cannot settle (in float32 with a refined 1/sqrt, then in float64), so the decisions are
    the float64 ones; an accepted pair's sum is then
    within its bound (~1e-5 relative in practice) of the exact one. ``float64``: every distance
    in float64 (sums to ~1e-13).

    count_rest: with early exit, a rejected pair's ``used`` also counts the points its sum did
    not reach (read for presence only), so ``used`` is every point both detections have, for
    every pair, and early exit changes only the rejected pairs' sums.
    """
    sums, used, _ = frame_sums_reached(
        points, F, cam_a, det_a, cam_b, det_b, tau, symmetric, early_exit, backend, precision, count_rest
    )
    return sums, used


def frame_sums_reached(
    points: Mapping[int, np.ndarray | PointRows],
    F: Mapping[tuple[int, int], np.ndarray] | PairMatrices,
    cam_a: np.ndarray,
    det_a: np.ndarray,
    cam_b: np.ndarray,
    det_b: np.ndarray,
    tau: float,
    symmetric: bool,
    early_exit: bool,
    backend: str,
    precision: str,
    count_rest: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`frame_sums` and, third, the points each pair's sum reached (``used`` without
    count_rest)."""
    plan = frame_pairs(points, F, cam_a, det_a, cam_b, det_b)
    return level_sums(
        plan, points, np.arange(plan.which.size), tau, symmetric, early_exit, backend, precision, count_rest
    )


@dataclass(frozen=True)
class FramePairs:
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


def frame_pairs(
    points: Mapping[int, np.ndarray | PointRows],
    F: Mapping[tuple[int, int], np.ndarray] | PairMatrices,
    cam_a: np.ndarray,
    det_a: np.ndarray,
    cam_b: np.ndarray,
    det_b: np.ndarray,
) -> FramePairs:
    """:class:`FramePairs` of pairs (det_a[s] of camera cam_a[s], det_b[s] of cam_b[s]) over
    the cameras' points; ValueError naming the first bad input."""
    pairs = [np.ascontiguousarray(v, dtype=np.int64) for v in (cam_a, det_a, cam_b, det_b)]
    if any(v.ndim != 1 or v.shape != pairs[0].shape for v in pairs):
        raise ValueError(
            f"epipolar pairs: cameras and detections must be equal-length 1D, got {[v.shape for v in pairs]}"
        )
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
    return FramePairs(
        cam_a, det_a, cam_b, det_b, cams, counts, offsets, keys[0], keys[1], which, Fs.unit, order
    )


def level_sums(
    plan: FramePairs,
    points: Mapping[int, np.ndarray | PointRows],
    todo: np.ndarray,
    tau: float,
    symmetric: bool,
    early_exit: bool,
    backend: str,
    precision: str,
    count_rest: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        raise ValueError(
            f"epipolar points: expected (N,n,2) with one n for every camera, got n={sorted(sizes)}"
        )
    if any(rows[c].count != k for c, k in zip(cams, plan.counts.tolist())):
        raise ValueError("epipolar points: a level's detections differ from the pairs' cameras'")
    n = sizes.pop() if sizes else 0
    S = todo.size
    if S == 0 or n == 0:
        return np.zeros(S), np.zeros(S, dtype=np.int64), np.zeros(S, dtype=np.int64)
    use_numba = backend == "numba" or (backend == "auto" and have_numba())
    if not use_numba:
        return _numpylevel_sums(
            plan, rows, todo, float(tau) if early_exit else np.inf, bool(symmetric), bool(count_rest)
        )
    if not have_numba():
        raise ValueError("backend: 'numba' requested but numba is not installed")
    return _numbalevel_sums(
        rows, plan, todo, n, float(tau), bool(symmetric), bool(early_exit), precision, bool(count_rest)
    )


def _numpylevel_sums(
    plan: FramePairs,
    rows: dict[int, PointRows],
    todo: np.ndarray,
    tau: float,
    symmetric: bool,
    count_rest: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The numpy reference on the plan's pairs todo, one camera pair at a time."""
    S = todo.size
    which = plan.which[todo]
    cam_a, det_a, cam_b, det_b = (v[todo] for v in (plan.cam_a, plan.det_a, plan.cam_b, plan.det_b))
    out = np.zeros(S), np.zeros(S, dtype=np.int64), np.zeros(S, dtype=np.int64)
    for g in sorted_unique(which).tolist():
        s = np.flatnonzero(which == g)
        for v, got in zip(
            out,
            _numpy_sums(
                rows[int(cam_a[s[0]])],
                rows[int(cam_b[s[0]])],
                plan.unit[g].reshape(3, 3),
                det_a[s],
                det_b[s],
                tau,
                symmetric,
                count_rest,
            ),
        ):
            v[s] = got
    return out


def _numbalevel_sums(
    rows: dict[int, PointRows],
    plan: FramePairs,
    todo: np.ndarray,
    n: int,
    tau: float,
    symmetric: bool,
    early_exit: bool,
    precision: str,
    count_rest: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
    mixed = precision == "mixed" and flats[0].dtype == np.float32 and rsqrt_within_bound()
    chosen = np.zeros(plan.which.size, bool)
    chosen[todo] = True
    order = plan.order[chosen[plan.order]]  # this level's pairs in the kernel's order
    key_a, key_b = plan.key_a[order], plan.key_b[order]
    # flats stay referenced during the call
    dets, rank, det_addr = detections_read(plan, key_a, key_b, flats, [rows[c].rows for c in cams])
    like = flats[0]
    layout = rows[cams[0]]
    ranges = _known_ranges([rows[c] for c in cams], dets, n, mixed)
    if layout.run:  # a subset read in runs: each detection's points gathered once, contiguous
        like = gather_buffer(dets.size * 2 * n, like.dtype).reshape(dets.size, 2 * n)
        numba_kernels().gather_runs(
            flats[0], det_addr, layout.run, layout.period, like, 0, np.empty((0, 0), like.dtype)
        )
        det_addr = like.ctypes.data + np.arange(dets.size, dtype=np.int64) * like.strides[0]
        like = like.reshape(-1)
    if like.flags.writeable:
        # one compiled kernel per dtype: a writable array would take another, compiled (and
        # cached) apart with its own inlining, so sums could differ in the last bits between
        # points read in place (read-only views) and gathered ones
        like = like.view()
        like.setflags(write=False)
    got = numba_kernels().sums_kernel(
        like,
        det_addr,
        ranges,
        plan.unit,
        plan.which[order],
        rank[key_a],
        rank[key_b],
        block_order(n),
        n,
        tau,
        early_exit,
        symmetric,
        mixed,
        mixed and refined_rsqrt_within_bound(),
        count_rest,
    )
    # back from the kernel's order to todo's
    at = np.empty(plan.which.size, np.int64)
    at[todo] = np.arange(todo.size)
    out = np.empty(todo.size), np.empty(todo.size, dtype=np.int64), np.empty(todo.size, np.int64)
    for v, g in zip(out, got):
        v[at[order]] = g
    return out


def detections_read(
    plan: FramePairs, key_a: np.ndarray, key_b: np.ndarray, flats: list[np.ndarray], rows: list[np.ndarray]
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
    camera's were not given (the kernel computes them when it first reads a block). Ranges
    made when the frame was prepared (PairGates.prepare) spare the kernel a pass over the
    points."""
    order = block_order(n)
    given = [r.ranges for r in rows]
    if not mixed or all(g is None for g in given):
        return np.full((dets.size, order.shape[0], 2), np.nan)
    natural = np.concatenate(
        [
            g if g is not None else np.full((r.count, order.shape[0], 2), np.nan, np.float32)
            for g, r in zip(given, rows)
        ]
    )
    return natural[dets][:, order[:, 0] // BLOCK].astype(np.float64)


#: per thread, the bytes the screens' gathered points are written to, kept from call to call
_scratch = threading.local()


def gather_buffer(size: int, dtype: np.dtype, slot: int = 0, align: int = 64) -> np.ndarray:
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
        raw = _scratch.raw[slot] = np.empty(
            max(need + need // 2, 2 * raw.size if raw is not None else 0), np.uint8
        )
    skip = -raw.ctypes.data % align
    return raw[skip : skip + need - align].view(dtype)


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernels for float32 mesh vertices and
    float64 keypoints now, so a node's first frame does not pay for it. No-op without numba."""
    if not have_numba():
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
    at_epipole = q <= EPIPOLE_NORM**2
    with np.errstate(divide="ignore", invalid="ignore"):
        d = e / np.sqrt(q)
        if symmetric:
            m0 = F[0, 0] * ub + F[1, 0] * vb + F[2, 0]
            m1 = F[0, 1] * ub + F[1, 1] * vb + F[2, 1]
            qb = m0 * m0 + m1 * m1
            at_epipole |= qb <= EPIPOLE_NORM**2
            d = 0.5 * (d + e / np.sqrt(qb))
    missing = np.isnan(ua + va + ub + vb)
    return np.where(missing, np.nan, np.where(at_epipole | np.isnan(d), np.inf, d))


def _numpy_sums(
    ra: PointRows,
    rb: PointRows,
    F: np.ndarray,
    ia: np.ndarray,
    jb: np.ndarray,
    tau: float,
    symmetric: bool,
    count_rest: bool,
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
    for idx in block_indices(ra.n):
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


def _block_points(
    ra: PointRows,
    rb: PointRows,
    ia: np.ndarray,
    jb: np.ndarray,
    idx: np.ndarray,
    F: np.ndarray,
    symmetric: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """(distances (S,m) px, present (S,m) bool) of points idx of the pairs (ia, jb)."""
    oa = ra.rows[ia, None] + 2 * ra.positions(idx)[None, :]
    ob = rb.rows[jb, None] + 2 * rb.positions(idx)[None, :]
    A = np.stack([ra.flat[oa], ra.flat[oa + 1]], axis=-1)
    B = np.stack([rb.flat[ob], rb.flat[ob + 1]], axis=-1)
    d = point_distances(A, B, F, symmetric)
    return d, ~np.isnan(d)


@lru_cache(maxsize=1)
def numba_kernels():
    """The numba kernels' module (compiled, or loaded from numba's on-disk cache, on first
    use)."""
    from maem_ros.core.association.gates import epipolar_kernel

    return epipolar_kernel
