"""Numba kernels of the consistent clustering (core.clustering): the merge check and the
cluster-level table update.

Both walk what the numpy paths compute with whole-array passes, per candidate and joint (the
check) or per merged row and column (the update), in the same float64 operations and order
(no fast-math). The one difference is the order of the 4-term dot products of the
reprojection (numpy hands them to a BLAS matmul): a relative difference of ~1e-16 in the
pixel errors the check compares with tau_verify.
"""
from __future__ import annotations

import numpy as np

from .geometry import _SINGULAR, adjugate_solve, normal_cofactors
from .jit import have_numba, jit

# geometry's elementwise formulas, compiled for the scalars here (one home: geometry)
_normal_cofactors = jit(normal_cofactors, inline=True)
_adjugate_solve = jit(adjugate_solve, inline=True)

def consistent(E: np.ndarray, P: np.ndarray, uv: np.ndarray, usable: np.ndarray,
               rows: np.ndarray, tau: float) -> np.ndarray:
    """(K,) whether every member of candidate k (rows[k], -1 = padding) has a median
    reprojection error (px, over its usable joints) under tau, the joints triangulated (DLT)
    from all members: clustering._Verifier's check.

    E (9,R,Jb) each row's DLT normal entries (0 where unusable), P (R,3,4) rectified
    projections, uv (R,Jb,2) px, usable (R,Jb) bool, rows (K,M) int64 < R.
    """
    ok = np.empty(rows.shape[0], np.bool_)
    _consistent(E, P, uv, usable, np.ascontiguousarray(rows, np.int64), float(tau), ok)
    return ok


def absorb(x: np.ndarray, y: np.ndarray, between: np.ndarray, support: np.ndarray) -> None:
    """Clusters y[k] merged into x[k] (all distinct) in the symmetric (N,N) tables between
    (float64) and support (int64), in place: rows x += rows y, then columns x += columns y,
    rows and columns y zeroed (clustering._absorb's matrix update)."""
    _absorb(np.ascontiguousarray(x, np.int64), np.ascontiguousarray(y, np.int64), between)
    _absorb(np.ascontiguousarray(x, np.int64), np.ascontiguousarray(y, np.int64), support)


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernels now. No-op without numba."""
    if not have_numba():
        return
    E = np.zeros((9, 2, 3))
    consistent(E, np.zeros((2, 3, 4)), np.zeros((2, 3, 2)), np.zeros((2, 3), bool),
               np.array([[0, -1]]), 1.0)
    absorb(np.array([0]), np.array([1]), np.zeros((2, 2)), np.zeros((2, 2), np.int64))


@jit
def _consistent(E, P, uv, usable, rows, tau, ok):
    Jb = E.shape[2]
    M = rows.shape[1]
    X = np.empty((Jb, 3))
    err = np.empty(Jb)
    n = np.empty(9)
    for k in range(rows.shape[0]):
        for j in range(Jb):  # the joints of all members (geometry.solve_normal)
            n[:] = 0.0
            for m in range(M):
                r = rows[k, m]
                if r >= 0:
                    for q in range(9):
                        n[q] += E[q, r, j]
            X[j, 0], X[j, 1], X[j, 2] = _solve(n)
        good = True
        for m in range(M):
            r = rows[k, m]
            if r < 0 or not good:
                continue
            count = 0
            for j in range(Jb):  # insertion sort of the usable joints' errors (a handful)
                if usable[r, j]:
                    e = _reprojection(P, r, X[j, 0], X[j, 1], X[j, 2], uv[r, j, 0], uv[r, j, 1])
                    at = count
                    while at > 0 and err[at - 1] > e:
                        err[at] = err[at - 1]
                        at -= 1
                    err[at] = e
                    count += 1
            if count == 0:
                good = False
                continue
            med = 0.5 * (err[(count - 1) // 2] + err[count // 2])
            good = med < tau
        ok[k] = good


@jit(inline=True)
def _solve(n):
    """geometry.solve_normal of one system's entries n (9,): (x, y, z), NaN if singular."""
    cof = _normal_cofactors(n[0], n[1], n[2], n[3], n[4], n[5])
    det, trace = cof[6], cof[7]
    if not abs(det) > _SINGULAR * trace * trace * trace:
        det = np.nan
    return _adjugate_solve(cof[:6], det, n[6], n[7], n[8])


@jit(inline=True)
def _reprojection(P, r, x, y, z, u, v):
    """geometry.reprojection_error of point (x, y, z) in view P[r] against (u, v) px: inf
    behind the camera or for non-finite input."""
    depth = P[r, 2, 0] * x + P[r, 2, 1] * y + P[r, 2, 2] * z + P[r, 2, 3]
    inv_z = 1.0 / depth
    du = (P[r, 0, 0] * x + P[r, 0, 1] * y + P[r, 0, 2] * z + P[r, 0, 3]) * inv_z
    du -= u
    du *= du
    dv = (P[r, 1, 0] * x + P[r, 1, 1] * y + P[r, 1, 2] * z + P[r, 1, 3]) * inv_z
    dv -= v
    dv *= dv
    e = np.sqrt(du + dv)
    if depth > 0 and np.isfinite(e):
        return e
    return np.inf


@jit
def _absorb(x, y, matrix):
    N = matrix.shape[0]
    for k in range(x.size):
        for c in range(N):
            matrix[x[k], c] += matrix[y[k], c]
    # columns after all rows (the entry of two merged clusters sums 4 parts), row by row (the
    # columns are strided); a column y is read, then zeroed
    for r in range(N):
        for k in range(x.size):
            matrix[r, x[k]] += matrix[r, y[k]]
            matrix[r, y[k]] = 0
    for k in range(x.size):
        for c in range(N):
            matrix[y[k], c] = 0
