"""Numba kernel of the closed-form PA-MPJPE (core.geometry.procrustes.pa_mpjpe_columns), per pair.

The numpy path runs ~150 vectorised steps over (S,) rows, each a pass over memory with its
own temporaries. This kernel walks the same steps per pair
with scalars: the same float64 operations in the same order (no fast-math: no reassociation,
no fused multiply-add); each detection's keypoints are centred once per call (not once per
pair: a detection takes part in many pairs), joints contiguous. Only
the einsum reductions (H, the squared norms) may sum in another order than numpy's, a
relative difference of ~1e-16 in the costs (bit-identical on 6,000 random pairs here;
test_association_fast_paths.py compares them). The key matrix and the rotation are
procrustes' own functions, compiled. Pairs with a near-degenerate eigenvalue
gap are flagged for the SVD path, as in numpy.
"""

from __future__ import annotations

import numpy as np

from maem_ros.core.geometry.procrustes_terms import (
    ADJ_ENTRY,
    ADJ_MINOR,
    ADJ_SIGN,
    fill_key_matrix,
    fill_rotation,
)
from maem_ros.core.jit import have_numba, jit

# the elementwise formulas of procrustes_terms, compiled for the scalars here
_fill_key_matrix = jit(fill_key_matrix, inline=True)
_fill_rotation = jit(fill_rotation, inline=True)

#: the adjugate table as kernel arguments (global arrays would keep numba from caching)
_ADJUGATE = (
    np.ascontiguousarray(ADJ_ENTRY, np.int64),
    np.ascontiguousarray(ADJ_MINOR, np.int64),
    np.ascontiguousarray(ADJ_SIGN, np.float64),
)


def pair_costs(
    columns: np.ndarray, a: np.ndarray, b: np.ndarray, max_steps: int, min_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """(costs (S,), closed form usable (S,) bool) of columns[:, :, a[s]] aligned onto
    columns[:, :, b[s]]: columns (3,J,N) float64 finite keypoints (J >= 3); a pair whose flag is
    False has no cost yet (NaN): its eigenvalue gap is too small (pa_mpjpe_columns)."""
    S = a.size
    out = np.empty(S)
    ok = np.empty(S, np.bool_)
    _kernel(
        np.ascontiguousarray(columns, dtype=np.float64),
        np.ascontiguousarray(a, np.int64),
        np.ascontiguousarray(b, np.int64),
        _ADJUGATE,
        int(max_steps),
        float(min_gap),
        out,
        ok,
    )
    return out, ok


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernel now. No-op without numba."""
    if have_numba():
        cols = np.random.default_rng(0).normal(size=(3, 4, 2))
        pair_costs(cols, np.array([0]), np.array([1]), 60, 1e-6)


@jit
def _centre(cols, n, xc, norm2):
    """Detection n's keypoints centred (once for all its pairs): xc[n] (3,J) = cols[:, :, n]
    minus their mean over joints (numpy: a sequential sum / J), norm2[n] = sum of xc[n]^2
    (coordinates outer, joints inner: pa_mpjpe_columns' order)."""
    J = cols.shape[1]
    for c in range(3):
        total = cols[c, 0, n]
        for j in range(1, J):
            total += cols[c, j, n]
        mean = total / J
        for j in range(J):
            xc[n, c, j] = cols[c, j, n] - mean
    acc = 0.0
    for c in range(3):
        for j in range(J):
            acc += xc[n, c, j] * xc[n, c, j]
    norm2[n] = acc


@jit(inline=True)
def _pair(centred, norm2, i, k, h, K, m, q, R, adj, max_steps, min_gap):
    """(cost, usable) of detection i onto k: pa_mpjpe_columns' steps for one pair on the
    centred keypoints (centred (N,3,J), norm2 (N,) from _centre); h (3,3), K (4,4), m (12,),
    q (4,), R (3,3) scratch (no allocation per pair); adj: procrustes' adjugate table
    (entries, minors, signs)."""
    J = centred.shape[2]
    xc = centred[i]
    yc = centred[k]
    for p in range(3):  # h: sum_j x_a y_b
        for o in range(3):
            acc = 0.0
            for j in range(J):
                acc += xc[p, j] * yc[o, j]
            h[p, o] = acc
    gx = norm2[i]
    gy = norm2[k]
    _fill_key_matrix(K, h[0, 0], h[0, 1], h[0, 2], h[1, 0], h[1, 1], h[1, 2], h[2, 0], h[2, 1], h[2, 2])
    f2 = 0.0
    for p in range(3):
        for o in range(3):
            f2 += h[p, o] * h[p, o]
    c2 = -2.0 * f2
    det3 = (
        h[0, 0] * (h[1, 1] * h[2, 2] - h[1, 2] * h[2, 1])
        - h[0, 1] * (h[1, 0] * h[2, 2] - h[1, 2] * h[2, 0])
        + h[0, 2] * (h[1, 0] * h[2, 1] - h[1, 1] * h[2, 0])
    )
    c1 = -8.0 * det3
    _minors(K, m)
    c0 = m[0] * m[11] - m[1] * m[10] + m[2] * m[9] + m[3] * m[8] - m[4] * m[7] + m[5] * m[6]
    frob = np.sqrt(f2)
    lam = min(np.sqrt(gx * gy), np.sqrt(3.0) * frob)
    tol = 1e-13 * frob
    active = True
    for _ in range(max_steps):  # Newton on the quartic from an upper bound (monotone)
        l2 = lam * lam
        p4 = (l2 + c2) * l2 + c1 * lam + c0
        dp = (4.0 * l2 + 2.0 * c2) * lam + c1
        step = p4 / dp if dp > 0 else 0.0
        lam -= step
        if not abs(step) > tol:
            active = False
            break
    l2 = lam * lam
    dp = (4.0 * l2 + 2.0 * c2) * lam + c1
    if active or not dp > min_gap * f2 * frob:
        return np.nan, False
    for d in range(4):
        K[d, d] -= lam
    _minors(K, m)
    best = 0  # the adjugate's column with the largest |diagonal| (first on ties, as argmax)
    best_val = -1.0
    for d in range(4):
        v = abs(_adjugate_entry(K, m, d, d, adj))
        if v > best_val:
            best, best_val = d, v
    for r in range(4):
        q[r] = _adjugate_entry(K, m, r, best, adj)
    norm = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    _fill_rotation(R, q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
    scale = lam / gx if gx > 0 else 0.0
    for p in range(3):
        for o in range(3):
            R[p, o] *= scale
    total = 0.0
    for j in range(J):
        sq = 0.0
        for p in range(3):
            r = R[p, 0] * xc[0, j]
            r += R[p, 1] * xc[1, j]
            r += R[p, 2] * xc[2, j]
            r -= yc[p, j]
            r *= r
            sq += r
        total += np.sqrt(sq)
    return total / J, True


@jit(inline=True)
def _minors(a, m):
    """m (12,) = the 2x2 minors of rows (0,1), then rows (2,3), of a (4,4), columns 01 02 03
    12 13 23 (procrustes._minors)."""
    for half in range(2):
        r0 = 2 * half
        r1 = r0 + 1
        k = 6 * half
        for ci, cj in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)):
            m[k] = a[r0, ci] * a[r1, cj] - a[r1, ci] * a[r0, cj]
            k += 1


@jit(inline=True)
def _adjugate_entry(a, m, r, c, adj):
    """adj(a)[r, c] from a (4,4) and its minors m: the three signed terms of
    procrustes._adjugate_table (adj = its entries, minors, signs) in its order."""
    entry, minor, sign = adj
    total = 0.0
    for t in range(3):
        e = entry[4 * r + c, t]
        term = a[e // 4, e % 4] * m[minor[4 * r + c, t]]
        total += term * sign[4 * r + c, t]
    return total


@jit
def _kernel(cols, a, b, adj, max_steps, min_gap, out, ok):
    centred = np.empty((cols.shape[2], 3, cols.shape[1]))
    norm2 = np.empty(cols.shape[2])
    done = np.zeros(cols.shape[2], np.bool_)  # centred already (only the pairs' detections)
    h = np.empty((3, 3))
    K = np.empty((4, 4))
    m = np.empty(12)
    q = np.empty(4)
    R = np.empty((3, 3))
    for s in range(a.size):
        for n in (a[s], b[s]):
            if not done[n]:
                _centre(cols, n, centred, norm2)
                done[n] = True
        out[s], ok[s] = _pair(centred, norm2, a[s], b[s], h, K, m, q, R, adj, max_steps, min_gap)
