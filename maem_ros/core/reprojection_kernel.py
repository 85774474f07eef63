"""The numba kernel of the association's bbox-centre reprojection gate (core/association.py),
imported only when numba is installed.

One pass over every candidate pair of a frame set (the pairs of core.association's
_enumerate_pairs, in its order) with nothing but scalars: the epipolar lower bound of
geometry.pair_reprojection_bound rejects most pairs, the others get the two-view DLT of
geometry.pair_reprojection_errors. The numpy path materialises ~20 arrays of the pair count
(75,000 pairs in 16 cameras x 25 detections: ~7 ms); this pass takes ~1 ms.

Decisions equal the numpy path's: the bound only rejects with a relative margin far above its
rounding (its arithmetic order does not matter), and the DLT and reprojection are the numpy
path's float64 operations in the same order (no fast-math: no reassociation, no fused
multiply-add), so the errors compared with tau are the same numbers.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from .geometry import _SINGULAR

_OPTS = dict(cache=True, error_model="numpy", boundscheck=False, nogil=True)


@nb.njit(**_OPTS)
def _normal_entries(P, uv, out):
    """out (N,9): geometry.normal_entries of each view (uv (N,2) px, P (N,3,4)), in its
    entry order and arithmetic; an unusable view (non-finite uv) takes uv = 0."""
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2), (0, 3), (1, 3), (2, 3))
    r1 = np.empty(4)
    r2 = np.empty(4)
    for n in range(P.shape[0]):
        u = uv[n, 0]
        v = uv[n, 1]
        if not (np.isfinite(u) and np.isfinite(v)):
            u = 0.0
            v = 0.0
        for k in range(4):
            r1[k] = u * P[n, 2, k] - P[n, 0, k]
            r2[k] = v * P[n, 2, k] - P[n, 1, k]
        for e in range(9):
            a, b = pairs[e]
            out[n, e] = r1[a] * r1[b] + r2[a] * r2[b]


@nb.njit(**_OPTS)
def _view_error(P, n, x0, x1, x2, u, v):
    """Reprojection error (px) of point (x0, x1, x2) in view n (P (N,3,4)); inf behind the
    camera or non-finite (geometry.pair_reprojection_errors' arithmetic)."""
    h0 = P[n, 0, 0] * x0 + P[n, 0, 1] * x1 + P[n, 0, 2] * x2 + P[n, 0, 3]
    h1 = P[n, 1, 0] * x0 + P[n, 1, 1] * x1 + P[n, 1, 2] * x2 + P[n, 1, 3]
    h2 = P[n, 2, 0] * x0 + P[n, 2, 1] * x1 + P[n, 2, 2] * x2 + P[n, 2, 3]
    du = h0 / h2 - u
    dv = h1 / h2 - v
    err = np.sqrt(du * du + dv * dv)
    return err if h2 > 0 and np.isfinite(err) else np.inf


@nb.njit(**_OPTS)
def _pair_error(P, uv, E, i, j, reduce_max):
    """geometry.pair_reprojection_errors of the pair (i, j): DLT from the summed normal
    entries (geometry.solve_normal), reprojected into both views, mean or max."""
    n00 = E[i, 0] + E[j, 0]
    n01 = E[i, 1] + E[j, 1]
    n02 = E[i, 2] + E[j, 2]
    n11 = E[i, 3] + E[j, 3]
    n12 = E[i, 4] + E[j, 4]
    n22 = E[i, 5] + E[j, 5]
    r0 = E[i, 6] + E[j, 6]
    r1 = E[i, 7] + E[j, 7]
    r2 = E[i, 8] + E[j, 8]
    c00 = n11 * n22 - n12 * n12
    c01 = n02 * n12 - n01 * n22
    c02 = n01 * n12 - n02 * n11
    c11 = n00 * n22 - n02 * n02
    c12 = n01 * n02 - n00 * n12
    c22 = n00 * n11 - n01 * n01
    det = n00 * c00 + n01 * c01 + n02 * c02
    trace = n00 + n11 + n22
    if not (abs(det) > _SINGULAR * trace * trace * trace):
        det = np.nan
    usable = (np.isfinite(uv[i, 0]) and np.isfinite(uv[i, 1]) and np.isfinite(uv[j, 0])
              and np.isfinite(uv[j, 1]))
    if not usable:
        return np.inf
    x0 = -((c00 * r0 + c01 * r1 + c02 * r2) / det)
    x1 = -((c01 * r0 + c11 * r1 + c12 * r2) / det)
    x2 = -((c02 * r0 + c12 * r1 + c22 * r2) / det)
    ei = _view_error(P, i, x0, x1, x2, uv[i, 0], uv[i, 1])
    ej = _view_error(P, j, x0, x1, x2, uv[j, 0], uv[j, 1])
    return max(ei, ej) if reduce_max else 0.5 * (ei + ej)


@nb.njit(**_OPTS)
def reprojection_gate(offsets, F, P, uv, tau, margin, reduce_max):
    """(i, j, ok) of every pair of rows (i in camera a, j in camera b, a < b; camera c's rows
    offsets[c]:offsets[c+1]) in core.association._enumerate_pairs' order; ok: bbox-centre
    reprojection error < tau px. F (C,C,3,3) as geometry.pair_reprojection_bound's, P (N,3,4)
    and uv (N,2) each row's projection and bbox centre (rectified px)."""
    C = offsets.shape[0] - 1
    S = 0
    for a in range(C):
        for b in range(a + 1, C):
            S += (offsets[a + 1] - offsets[a]) * (offsets[b + 1] - offsets[b])
    pi = np.empty(S, dtype=np.int64)
    pj = np.empty(S, dtype=np.int64)
    ok = np.zeros(S, dtype=np.bool_)
    E = np.empty((P.shape[0], 9))
    _normal_entries(P, uv, E)
    scale = 0.5 if not reduce_max else np.sqrt(0.5)
    limit = tau * (1.0 + margin)
    s = 0
    for a in range(C):
        for b in range(a + 1, C):
            f = F[a, b]
            cross = np.sqrt(f[0, 0] ** 2 + f[0, 1] ** 2 + f[1, 0] ** 2 + f[1, 1] ** 2)
            for i in range(offsets[a], offsets[a + 1]):
                ua = uv[i, 0]
                va = uv[i, 1]
                # F x_a: the line of x_a in b (and the gradient of g in x_b)
                l0 = f[0, 0] * ua + f[0, 1] * va + f[0, 2]
                l1 = f[1, 0] * ua + f[1, 1] * va + f[1, 2]
                l2 = f[2, 0] * ua + f[2, 1] * va + f[2, 2]
                for j in range(offsets[b], offsets[b + 1]):
                    ub = uv[j, 0]
                    vb = uv[j, 1]
                    # F^T x_b: the gradient of g in x_a
                    m0 = f[0, 0] * ub + f[1, 0] * vb + f[2, 0]
                    m1 = f[0, 1] * ub + f[1, 1] * vb + f[2, 1]
                    g = abs(l0 * ub + l1 * vb + l2)
                    grad = np.sqrt(l0 * l0 + l1 * l1 + m0 * m0 + m1 * m1)
                    bound = scale * 2.0 * g / (grad + np.sqrt(grad * grad + 2.0 * cross * g))
                    pi[s] = i
                    pj[s] = j
                    # NaN bound (degenerate geometry): no bound, the DLT decides
                    if not bound > limit:
                        ok[s] = _pair_error(P, uv, E, i, j, reduce_max) < tau
                    s += 1
    return pi, pj, ok
