"""Fused numba kernel of the per-keypoint RANSAC triangulation (core.triangulation).

The numpy path (core.triangulation._ransac_numpy) materialises every hypothesis' reprojection
into every view as (C,M,Q,J) arrays: ~15 memory passes over 3 M doubles for 22 people in 16
cameras (Q = 120 view pairs). This kernel walks the same computation per cluster and keypoint
with nothing but a few scalars and an (M,9) scratch of normal-matrix entries, in the same
float64 operations in the same order (no fast-math: no reassociation, no fused multiply-add),
so its hypotheses, inlier sets, best hypothesis (first of the highest key, as numpy's argmax)
and weighted refit are those of the numpy path. The one difference is the order of the
4-term dot products of the projection (numpy hands them to a BLAS matmul), a relative
difference of ~1e-16 in the pixel errors; see test_triangulation_kernel.py.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from .geometry import _SINGULAR

try:  # numba is optional: the numpy path gives the same results, only slower
    import numba as _numba
except ImportError:  # pragma: no cover - exercised only without numba
    _numba = None

BACKENDS = ("auto", "numba", "numpy")


def have_numba() -> bool:
    return _numba is not None


def use_numba(backend: str) -> bool:
    """Whether ``backend`` (auto | numba | numpy) runs the numba kernel; ValueError when numba
    is requested but not installed."""
    if backend == "numba" and _numba is None:
        raise ValueError("ransac_backend: 'numba' requested but numba is not installed")
    return backend == "numba" or (backend == "auto" and _numba is not None)


def ransac_keypoints(P: np.ndarray, uv: np.ndarray, usable: np.ndarray, weight: np.ndarray,
                     tau: float, min_views: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-keypoint RANSAC over view-pair hypotheses and score-weighted refit (numba).

    P (C,M,3,4) rectified world->px per member; uv (C,M,J,2) px; usable (C,M,J) bool (present
    and finite); weight (C,M) DLT weight per member; tau px inlier threshold; min_views.
    Returns X (C,J,3) world m (NaN where fewer than min_views inliers or singular) and the
    inlier views per keypoint (C,J) int64 (0 where X is NaN).
    """
    C, M, J = usable.shape
    X = np.empty((C, J, 3))
    n_inl = np.empty((C, J), np.int64)
    _kernel()(np.ascontiguousarray(P, dtype=np.float64), np.ascontiguousarray(uv, np.float64),
              np.ascontiguousarray(usable, np.bool_), np.ascontiguousarray(weight, np.float64),
              float(tau), int(min_views), X, n_inl)
    return X, n_inl


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernel now, so a node's first frame
    does not pay for it. No-op without numba."""
    if _numba is not None:
        ransac_keypoints(np.zeros((1, 2, 3, 4)), np.zeros((1, 2, 1, 2)), np.ones((1, 2, 1), bool),
                         np.ones((1, 2)), 1.0, 2)


@lru_cache(maxsize=1)
def _kernel():
    """Compile (or load from the on-disk cache) the kernel on first use."""
    jit = _numba.njit(cache=True, error_model="numpy", boundscheck=False, nogil=True)
    singular_eps = _SINGULAR

    @jit
    def entries(P, u, v, out):
        """geometry.normal_entries of one view into out (9,): rows r1 = u P3 - P1, r2 = v P3 - P2."""
        a0 = u * P[2, 0] - P[0, 0]
        a1 = u * P[2, 1] - P[0, 1]
        a2 = u * P[2, 2] - P[0, 2]
        a3 = u * P[2, 3] - P[0, 3]
        b0 = v * P[2, 0] - P[1, 0]
        b1 = v * P[2, 1] - P[1, 1]
        b2 = v * P[2, 2] - P[1, 2]
        b3 = v * P[2, 3] - P[1, 3]
        out[0] = a0 * a0 + b0 * b0
        out[1] = a0 * a1 + b0 * b1
        out[2] = a0 * a2 + b0 * b2
        out[3] = a1 * a1 + b1 * b1
        out[4] = a1 * a2 + b1 * b2
        out[5] = a2 * a2 + b2 * b2
        out[6] = a0 * a3 + b0 * b3
        out[7] = a1 * a3 + b1 * b3
        out[8] = a2 * a3 + b2 * b3

    @jit
    def solve(n, X):
        """geometry.solve_normal of one system n (9,) into X (3,), NaN when singular."""
        c00 = n[3] * n[5] - n[4] * n[4]
        c01 = n[2] * n[4] - n[1] * n[5]
        c02 = n[1] * n[4] - n[2] * n[3]
        c11 = n[0] * n[5] - n[2] * n[2]
        c12 = n[1] * n[2] - n[0] * n[4]
        c22 = n[0] * n[3] - n[1] * n[1]
        det = n[0] * c00 + n[1] * c01 + n[2] * c02
        trace = n[0] + n[3] + n[5]
        if not (abs(det) > singular_eps * trace * trace * trace):
            det = np.nan
        X[0] = -((c00 * n[6] + c01 * n[7] + c02 * n[8]) / det)
        X[1] = -((c01 * n[6] + c11 * n[7] + c12 * n[8]) / det)
        X[2] = -((c02 * n[6] + c12 * n[7] + c22 * n[8]) / det)

    @jit
    def error(P, X, u, v):
        """geometry.reprojection_error of X (3,) in one view: px, inf behind the camera or
        for non-finite input."""
        z = P[2, 0] * X[0] + P[2, 1] * X[1] + P[2, 2] * X[2] + P[2, 3]
        inv_z = 1.0 / z
        du = (P[0, 0] * X[0] + P[0, 1] * X[1] + P[0, 2] * X[2] + P[0, 3]) * inv_z - u
        dv = (P[1, 0] * X[0] + P[1, 1] * X[1] + P[1, 2] * X[2] + P[1, 3]) * inv_z - v
        err = np.sqrt(du * du + dv * dv)
        if z > 0 and np.isfinite(err):
            return err
        return np.inf

    @jit
    def kernel(P, uv, usable, weight, tau, min_views, X_out, n_out):
        C, M, J = usable.shape
        E = np.empty((M, 9))
        pair = np.empty(9)
        hyp = np.empty(3)
        inl = np.empty(M, np.bool_)
        best_inl = np.empty(M, np.bool_)
        w2 = np.empty(M)
        for c in range(C):
            for m in range(M):
                w2[m] = weight[c, m] * weight[c, m]
            for j in range(J):
                for m in range(M):
                    if usable[c, m, j]:
                        entries(P[c, m], uv[c, m, j, 0], uv[c, m, j, 1], E[m])
                    else:  # geometry.normal_entries: unusable views get uv = 0
                        entries(P[c, m], 0.0, 0.0, E[m])
                best_key = -np.inf
                best_count = 0
                best_inl[:] = False
                for a in range(M):  # view pairs in np.triu_indices(M, 1) order
                    for b in range(a + 1, M):
                        if usable[c, a, j] and usable[c, b, j]:
                            for e in range(9):
                                pair[e] = E[a, e] + E[b, e]
                            solve(pair, hyp)
                        else:
                            hyp[:] = np.nan
                        count = 0
                        total = 0.0
                        for m in range(M):
                            inl[m] = False
                            if usable[c, m, j]:
                                err = error(P[c, m], hyp, uv[c, m, j, 0], uv[c, m, j, 1])
                                if err < tau:
                                    inl[m] = True
                                    count += 1
                                    total += err
                        if np.isfinite(hyp[0]):
                            key = count - (total / max(count, 1)) / (2.0 * tau)
                        else:
                            key = -1.0
                        if key > best_key:  # strict: the first of equal keys, as argmax
                            best_key = key
                            best_count = count
                            best_inl[:] = inl
                # score-weighted refit from the best hypothesis' inliers (weight^2 x entries,
                # summed in view order, as (E * w2).sum over views)
                for e in range(9):
                    pair[e] = 0.0
                for m in range(M):
                    if best_inl[m]:
                        for e in range(9):
                            pair[e] += E[m, e] * w2[m]
                solve(pair, hyp)
                finite = np.isfinite(hyp[0]) and np.isfinite(hyp[1]) and np.isfinite(hyp[2])
                if best_count >= min_views and finite:
                    X_out[c, j, 0] = hyp[0]
                    X_out[c, j, 1] = hyp[1]
                    X_out[c, j, 2] = hyp[2]
                    n_out[c, j] = best_count
                else:
                    X_out[c, j, :] = np.nan
                    n_out[c, j] = 0

    return kernel
