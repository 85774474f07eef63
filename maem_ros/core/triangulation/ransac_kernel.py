"""Fused numba kernel of the per-keypoint RANSAC triangulation (core.triangulation.ransac).

The numpy path (core.triangulation.ransac._ransac_numpy) materialises every hypothesis' reprojection
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

import numpy as np

from maem_ros.core.geometry.multiview_kernel import SINGULAR, view_entries
from maem_ros.core.jit import have_numba, jit

BACKENDS = ("auto", "numba", "numpy")


def use_numba(backend: str) -> bool:
    """Whether ``backend`` (auto | numba | numpy) runs the numba kernel; ValueError when numba
    is requested but not installed."""
    if backend == "numba" and not have_numba():
        raise ValueError("ransac_backend: 'numba' requested but numba is not installed")
    return backend == "numba" or (backend == "auto" and have_numba())


def ransac_keypoints(
    P: np.ndarray, uv: np.ndarray, usable: np.ndarray, weight: np.ndarray, tau: float, min_views: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per-keypoint RANSAC over view-pair hypotheses and score-weighted refit (numba).

    P (C,M,3,4) rectified world->px per member; uv (C,M,J,2) px; usable (C,M,J) bool (present
    and finite); weight (C,M) DLT weight per member; tau px inlier threshold; min_views.
    Returns X (C,J,3) world m (NaN where fewer than min_views inliers or singular) and the
    inlier views per keypoint (C,J) int64 (0 where X is NaN).
    """
    C, M, J = usable.shape
    X = np.empty((C, J, 3))
    n_inl = np.empty((C, J), np.int64)
    uv = np.asarray(uv, dtype=np.float64)
    _kernel(
        np.ascontiguousarray(P, dtype=np.float64),
        np.ascontiguousarray(uv[..., 0]),
        np.ascontiguousarray(uv[..., 1]),
        np.ascontiguousarray(usable, np.bool_),
        np.ascontiguousarray(weight, np.float64),
        float(tau),
        int(min_views),
        X,
        n_inl,
    )
    return X, n_inl


def warmup() -> None:
    """Compile (or load from numba's on-disk cache) the kernel now, so a node's first frame
    does not pay for it. No-op without numba."""
    if have_numba():
        ransac_keypoints(
            np.zeros((1, 2, 3, 4)), np.zeros((1, 2, 1, 2)), np.ones((1, 2, 1), bool), np.ones((1, 2)), 1.0, 2
        )


# every loop below runs over the keypoints j innermost (contiguous, independent): LLVM
# vectorises them with exact SIMD division and square root, no fast-math needed


@jit
def _solve(n, X):
    """geometry.solve_normal of the systems n (9,J) into X (3,J), NaN when singular."""
    for j in range(n.shape[1]):
        c00 = n[3, j] * n[5, j] - n[4, j] * n[4, j]
        c01 = n[2, j] * n[4, j] - n[1, j] * n[5, j]
        c02 = n[1, j] * n[4, j] - n[2, j] * n[3, j]
        c11 = n[0, j] * n[5, j] - n[2, j] * n[2, j]
        c12 = n[1, j] * n[2, j] - n[0, j] * n[4, j]
        c22 = n[0, j] * n[3, j] - n[1, j] * n[1, j]
        det = n[0, j] * c00 + n[1, j] * c01 + n[2, j] * c02
        trace = n[0, j] + n[3, j] + n[5, j]
        if not (abs(det) > SINGULAR * trace * trace * trace):
            det = np.nan
        X[0, j] = -((c00 * n[6, j] + c01 * n[7, j] + c02 * n[8, j]) / det)
        X[1, j] = -((c01 * n[6, j] + c11 * n[7, j] + c12 * n[8, j]) / det)
        X[2, j] = -((c02 * n[6, j] + c12 * n[7, j] + c22 * n[8, j]) / det)


@jit
def _score(P, X, u, v, usable, tau, inl, count, total):
    """Inliers of hypotheses X (3,J) in one view (P (3,4), u, v, usable (J,)): inl (J,)
    and the running count and error sum (px) per keypoint. An inlier has depth > 0 and
    error < tau (geometry.reprojection_error's inf fails that test too)."""
    for j in range(u.shape[0]):
        z = P[2, 0] * X[0, j] + P[2, 1] * X[1, j] + P[2, 2] * X[2, j] + P[2, 3]
        inv_z = 1.0 / z
        du = (P[0, 0] * X[0, j] + P[0, 1] * X[1, j] + P[0, 2] * X[2, j] + P[0, 3]) * inv_z - u[j]
        dv = (P[1, 0] * X[0, j] + P[1, 1] * X[1, j] + P[1, 2] * X[2, j] + P[1, 3]) * inv_z - v[j]
        err = np.sqrt(du * du + dv * dv)
        ok = usable[j] and z > 0 and err < tau
        inl[j] = ok
        count[j] += 1 if ok else 0
        total[j] += err if ok else 0.0


@jit
def _kernel(P, u, v, usable, weight, tau, min_views, X_out, n_out):
    """ransac_keypoints on split coordinates u, v (C,M,J), into X_out (C,J,3), n_out (C,J)."""
    C, M, J = usable.shape
    E = np.empty((M, 9, J))
    pair = np.empty((9, J))
    hyp = np.empty((3, J))
    inl = np.empty((M, J), np.bool_)
    best_hyp = np.empty((3, J))
    best_key = np.empty(J)
    count = np.empty(J, np.int64)
    total = np.empty(J)
    for c in range(C):
        for m in range(M):
            view_entries(P[c, m], u[c, m], v[c, m], usable[c, m], E[m])
        best_key[:] = -np.inf
        for a in range(M):  # view pairs in np.triu_indices(M, 1) order
            for b in range(a + 1, M):
                for e in range(9):
                    for j in range(J):
                        pair[e, j] = E[a, e, j] + E[b, e, j]
                _solve(pair, hyp)
                for j in range(J):
                    if not (usable[c, a, j] and usable[c, b, j]):
                        hyp[0, j] = hyp[1, j] = hyp[2, j] = np.nan
                count[:] = 0
                total[:] = 0.0
                for m in range(M):
                    _score(P[c, m], hyp, u[c, m], v[c, m], usable[c, m], tau, inl[m], count, total)
                for j in range(J):
                    # most inliers first; mean error / (2 tau) < 0.5 breaks ties
                    key = (
                        count[j] - (total[j] / max(count[j], 1)) / (2.0 * tau)
                        if np.isfinite(hyp[0, j])
                        else -1.0
                    )
                    if key > best_key[j]:  # strict: the first of equal keys
                        best_key[j] = key
                        best_hyp[0, j] = hyp[0, j]
                        best_hyp[1, j] = hyp[1, j]
                        best_hyp[2, j] = hyp[2, j]
        # the best hypotheses' inliers again (the same operations: the same inliers), then the
        # score-weighted refit from them: weight^2 x entries summed in view order, as
        # (E * w2).sum over views
        count[:] = 0
        total[:] = 0.0
        for m in range(M):
            _score(P[c, m], best_hyp, u[c, m], v[c, m], usable[c, m], tau, inl[m], count, total)
        pair[:] = 0.0
        for m in range(M):
            w2 = weight[c, m] * weight[c, m]
            for e in range(9):
                for j in range(J):
                    if inl[m, j]:
                        pair[e, j] += E[m, e, j] * w2
        _solve(pair, hyp)
        for j in range(J):
            finite = np.isfinite(hyp[0, j]) and np.isfinite(hyp[1, j]) and np.isfinite(hyp[2, j])
            if count[j] >= min_views and finite:
                X_out[c, j, 0] = hyp[0, j]
                X_out[c, j, 1] = hyp[1, j]
                X_out[c, j, 2] = hyp[2, j]
                n_out[c, j] = count[j]
            else:
                X_out[c, j, 0] = X_out[c, j, 1] = X_out[c, j, 2] = np.nan
                n_out[c, j] = 0
