"""The numba kernel of the bbox-centre reprojection gate (gates/reprojection.py), imported only
when numba is installed.

One pass over every candidate pair of a frame set (the pairs of reprojection.enumerate_pairs,
in its order) with nothing but scalars: the epipolar lower bound of
geometry.pair_reprojection_bound rejects most pairs, the others get the two-view DLT of
geometry.pair_reprojection_errors. The numpy path materialises ~20 arrays of the pair count
(75,000 pairs in 16 cameras x 25 detections); this pass keeps everything in registers and is
several times faster.

Decisions equal the numpy path's: the bound only rejects with a relative margin far above its
rounding (its arithmetic order does not matter), and the DLT and reprojection are the numpy
path's float64 operations in the same order (no fast-math: no reassociation, no fused
multiply-add), so the errors compared with tau are the same numbers. The DLT steps are
core.geometry.multiview_kernel's (multiview's normal entries and cofactor solve, compiled
for scalars).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from maem_ros.core.geometry.multiview_kernel import SINGULAR, adjugate, cofactors, view_entries
from maem_ros.core.jit import NjitOptions

_OPTS: NjitOptions = dict(cache=True, error_model="numpy", boundscheck=False, nogil=True)


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
def _pair_errors(P, U, V, usable, E, pi, pj, todo, reduce_max, tau, ok):
    """ok[s] = geometry.pair_reprojection_errors of the pairs s in todo (rows pi[s], pj[s])
    < tau: the DLT from the summed normal entries (E (9,N) each view's;
    geometry.solve_normal's arithmetic), reprojected into both views, mean or max. Scalars
    only, in one loop over the pairs the bounds kept."""
    for t in range(todo.shape[0]):
        s = todo[t]
        i = pi[s]
        j = pj[s]
        n0, n1, n2 = E[0, i] + E[0, j], E[1, i] + E[1, j], E[2, i] + E[2, j]
        n3, n4, n5 = E[3, i] + E[3, j], E[4, i] + E[4, j], E[5, i] + E[5, j]
        cof = cofactors(n0, n1, n2, n3, n4, n5)
        det, trace = cof[6], cof[7]
        if not abs(det) > SINGULAR * trace * trace * trace:
            det = np.nan
        x0, x1, x2 = adjugate(cof[:6], det, E[6, i] + E[6, j], E[7, i] + E[7, j], E[8, i] + E[8, j])
        ei = _view_error(P, i, x0, x1, x2, U[i], V[i])
        ej = _view_error(P, j, x0, x1, x2, U[j], V[j])
        err = max(ei, ej) if reduce_max else 0.5 * (ei + ej)
        ok[s] = usable[i] and usable[j] and err < tau


@nb.njit(**_OPTS)
def reprojection_gate(offsets, F, P, uv, tau, margin, reduce_max):
    """(i, j, ok) of every pair of rows (i in camera a, j in camera b, a < b; camera c's rows
    offsets[c]:offsets[c+1]) in reprojection.enumerate_pairs' order; ok: bbox-centre
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
    N = P.shape[0]
    usable = np.empty(N, dtype=np.bool_)
    for n in range(N):
        usable[n] = np.isfinite(uv[n, 0]) and np.isfinite(uv[n, 1])
    E = np.empty((9, N))  # each view's share of every pair's DLT system
    for n in range(N):
        view_entries(P[n], uv[n : n + 1, 0], uv[n : n + 1, 1], usable[n : n + 1], E[:, n : n + 1])
    scale = 0.5 if not reduce_max else np.sqrt(0.5)
    limit = tau * (1.0 + margin)
    # the centres' coordinates apart and contiguous, and one camera's bounds at a time: the
    # bound loop has no branch and vectorises; the DLT runs after all of them, in one loop
    # over the pairs they keep
    U = np.ascontiguousarray(uv[:, 0])
    V = np.ascontiguousarray(uv[:, 1])
    bound = np.empty(N)
    todo = np.empty(S, dtype=np.int64)  # the pairs the bounds keep, for the DLT
    m = 0
    s = 0
    for a in range(C):
        for b in range(a + 1, C):
            f = F[a, b]
            cross = np.sqrt(f[0, 0] ** 2 + f[0, 1] ** 2 + f[1, 0] ** 2 + f[1, 1] ** 2)
            lo, hi = offsets[b], offsets[b + 1]
            for i in range(offsets[a], offsets[a + 1]):
                # F x_a: the line of x_a in b (and the gradient of g in x_b)
                l0 = f[0, 0] * U[i] + f[0, 1] * V[i] + f[0, 2]
                l1 = f[1, 0] * U[i] + f[1, 1] * V[i] + f[1, 2]
                l2 = f[2, 0] * U[i] + f[2, 1] * V[i] + f[2, 2]
                _bounds(f, l0, l1, l2, cross, scale, U[lo:hi], V[lo:hi], bound)
                for k in range(hi - lo):
                    pi[s] = i
                    pj[s] = lo + k
                    # NaN bound (degenerate geometry): no bound, the DLT decides
                    if not bound[k] > limit:
                        todo[m] = s
                        m += 1
                    s += 1
    _pair_errors(P, U, V, usable, E, pi, pj, todo[:m], reduce_max, tau, ok)
    return pi, pj, ok


@nb.njit(inline="always", **_OPTS)
def _bounds(f, l0, l1, l2, cross, scale, ub, vb, out):
    """out[k] = the epipolar lower bound (geometry.pair_reprojection_bound's arithmetic) of
    the reprojection error of centre (ub[k], vb[k]) in b against the one whose line in b is
    (l0, l1, l2), under F f (3,3) with cross the norm of its upper-left 2x2 block."""
    for k in range(ub.shape[0]):
        # F^T x_b: the gradient of g in x_a
        m0 = f[0, 0] * ub[k] + f[1, 0] * vb[k] + f[2, 0]
        m1 = f[0, 1] * ub[k] + f[1, 1] * vb[k] + f[2, 1]
        g = abs(l0 * ub[k] + l1 * vb[k] + l2)
        grad = np.sqrt(l0 * l0 + l1 * l1 + m0 * m0 + m1 * m1)
        out[k] = scale * 2.0 * g / (grad + np.sqrt(grad * grad + 2.0 * cross * g))
