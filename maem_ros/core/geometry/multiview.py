"""Multi-view geometry shared by association and triangulation (rectified pinhole px, world m).

Batched inhomogeneous DLT (X4 = 1) with a closed-form 3x3 normal-equation solve, two-view
reprojection errors for the association's bbox-centre gate (and a rigorous lower bound of
them from the epipolar geometry, which settles most pairs without triangulating), and the
reprojection errors of point hypotheses in member views used by the RANSAC triangulation and
the cluster check.
"""

from __future__ import annotations

import numpy as np

#: relative determinant below which the normal equations are treated as singular
SINGULAR = 1e-13


def dlt(P: np.ndarray, uv: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Batched weighted linear triangulation.

    P (...,M,3,4) world -> px projection matrices; uv (...,M,2) px; w (...,M) view weights
    or None (all 1). Leading dims broadcast. Each view contributes the two DLT rows
    ``u P3 - P1`` and ``v P3 - P2`` scaled by its weight; the point minimises the weighted
    algebraic error with X4 = 1 (inhomogeneous DLT, Hartley & Zisserman §12.2; invariant
    to the choice of world origin, unlike the ||X|| = 1 form). Views with non-finite uv or
    weight <= 0 are ignored. Returns (...,3) world points; NaN where fewer than two views
    remain or the views are degenerate (coincident rays).
    """
    P = np.asarray(P, dtype=np.float64)
    uv = np.asarray(uv, dtype=np.float64)
    if P.shape[-2:] != (3, 4) or P.ndim < 3:
        raise ValueError(f"dlt: P must be (...,M,3,4), got {P.shape}")
    if uv.ndim < 2 or uv.shape[-1] != 2:
        raise ValueError(f"dlt: uv must be (...,M,2), got {uv.shape}")
    w = np.ones(uv.shape[:-1]) if w is None else np.asarray(w, dtype=np.float64)
    usable = np.isfinite(uv).all(-1) & np.isfinite(w) & (w > 0)
    E = normal_entries(P, uv, usable) * np.where(usable, w * w, 0.0)
    X = solve_normal(E.sum(-1))
    return np.where((usable.sum(-1) >= 2)[..., None], X, np.nan)


def normal_entries(P: np.ndarray, uv: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """(9,...) per-view DLT normal-matrix entries N = r1 r1^T + r2 r2^T, r1 = u P3 - P1, r2 = v P3 - P2.

    Entries in the order n00 n01 n02 n11 n12 n22 n03 n13 n23 (the only ones the X4 = 1
    solve needs), entry axis first so every later operation runs on contiguous arrays.
    Summing over views (times squared weights) gives the system of any view subset, so
    pair hypotheses and the final fit reuse one computation. Unusable views get uv = 0 (finite
    rows, not zeros): callers weight them by 0.
    """
    uv0 = np.where(usable[..., None], uv, 0.0)
    u, v = uv0[..., 0], uv0[..., 1]
    r1 = [u * P[..., 2, k] - P[..., 0, k] for k in range(4)]
    r2 = [v * P[..., 2, k] - P[..., 1, k] for k in range(4)]
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2), (0, 3), (1, 3), (2, 3))
    return np.stack([r1[i] * r1[j] + r2[i] * r2[j] for i, j in pairs])


def solve_normal(E: np.ndarray) -> np.ndarray:
    """(...,3) minimiser with X4 = 1 of X^T N X for normal matrices given as entries E (9,...).

    Closed-form adjugate solve of the 3x3 block, elementwise over the stack (numpy's
    per-matrix LAPACK calls cost microseconds each, far too slow for ~10^4 systems).
    NaN where the 3x3 block is (near) singular, e.g. fewer than two distinct rays.
    """
    shape = E.shape[1:]
    E = E.reshape(9, -1)
    cof = normal_cofactors(E[0], E[1], E[2], E[3], E[4], E[5])
    det, trace = cof[6], cof[7]
    det[~(np.abs(det) > SINGULAR * trace * trace * trace)] = np.nan  # singular
    # computed coordinate-first (contiguous) and returned as a (...,3) view
    X = np.stack(adjugate_solve(cof[:6], det, E[6], E[7], E[8]))
    return np.moveaxis(X.reshape((3,) + shape), 0, -1)


def normal_cofactors(n00, n01, n02, n11, n12, n22):
    """(c00, c01, c02, c11, c12, c22, det, trace) of the symmetric 3x3 block of DLT normal
    matrices (entries as in :func:`normal_entries`), elementwise: arrays here, scalars in the
    numba kernels that compile this same function."""
    c00 = n11 * n22 - n12 * n12
    c01 = n02 * n12 - n01 * n22
    c02 = n01 * n12 - n02 * n11
    c11 = n00 * n22 - n02 * n02
    c12 = n01 * n02 - n00 * n12
    c22 = n00 * n11 - n01 * n01
    det = n00 * c00 + n01 * c01 + n02 * c02
    trace = n00 + n11 + n22
    return c00, c01, c02, c11, c12, c22, det, trace


def adjugate_solve(cof, det, r0, r1, r2):
    """(x, y, z) = -adj(N) r / det from the cofactors cof (c00, c01, c02, c11, c12, c22) of
    :func:`normal_cofactors` and r = (r0, r1, r2) (normal entries n03 n13 n23), elementwise."""
    c00, c01, c02, c11, c12, c22 = cof
    x = c00 * r0  # unrolled, no helpers: numba compiles this function as it is
    x += c01 * r1
    x += c02 * r2
    x /= det
    y = c01 * r0
    y += c11 * r1
    y += c12 * r2
    y /= det
    z = c02 * r0
    z += c12 * r1
    z += c22 * r2
    z /= det
    return -x, -y, -z


def reprojection_error(P: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(C,M,Q,J) px errors of hypotheses X (C,Q,J,3) in views P (C,M,3,4) against uv (C,M,J,2).

    Inf for points behind the camera (depth <= 0) or non-finite input.
    """
    C, M = P.shape[:2]
    Q, J = X.shape[1:3]
    # homogeneous points coordinate-first (solve_normal's layout: no copy there), then one
    # batched GEMM per image coordinate: (C,M,4) @ (C,4,Q*J), contiguous results
    Xh = np.empty((4, C, Q, J))
    Xh[:3] = np.moveaxis(X, -1, 0)
    Xh[3] = 1.0
    Xh = Xh.reshape(4, C, Q * J).transpose(1, 0, 2)  # type: ignore[assignment]  # (C,4,Q*J) view
    Pk = np.moveaxis(P, 2, 0)  # (3,C,M,4)
    z = np.matmul(Pk[2], Xh).reshape(C, M, Q, J)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / z
        err = np.matmul(Pk[0], Xh).reshape(C, M, Q, J)
        err *= inv_z
        err -= uv[:, :, None, :, 0]
        err *= err
        dv = np.matmul(Pk[1], Xh).reshape(C, M, Q, J)
        dv *= inv_z
        dv -= uv[:, :, None, :, 1]
        dv *= dv
        err += dv
        np.sqrt(err, out=err)
    err[~((z > 0) & np.isfinite(err))] = np.inf
    return err


def reprojection_errors(P: np.ndarray, uv: np.ndarray, reduce: str = "mean") -> np.ndarray:
    """(S,) px bbox-centre reprojection error of S two-view pairs.

    P (S,2,3,4) world -> rectified px; uv (S,2,2) the two centres. See pair_reprojection_errors.
    """
    S = P.shape[0]
    first = np.arange(0, 2 * S, 2)
    return pair_reprojection_errors(P.reshape(2 * S, 3, 4), uv.reshape(2 * S, 2), first, first + 1, reduce)


def pair_reprojection_errors(
    P: np.ndarray, uv: np.ndarray, i: np.ndarray, j: np.ndarray, reduce: str = "mean"
) -> np.ndarray:
    """(S,) px reprojection error of the two-view pairs (i[s], j[s]) of N single views.

    P (N,3,4) world -> rectified px and uv (N,2) px of each view (e.g. one detection's bbox
    centre in its camera). Each pair's point is DLT-triangulated (dlt, from the two views'
    normal entries, computed once per view) and reprojected into both views; the two errors
    are reduced by ``mean`` or ``max``. Inf when the point is behind either camera or the
    rays are degenerate.
    """
    usable = np.isfinite(uv).all(-1)
    E = normal_entries(P, uv, usable)  # (9,N): one view's share of every pair's system
    X = solve_normal(E[:, i] + E[:, j])  # (S,3)
    X[~(usable[i] & usable[j])] = np.nan
    errors = []
    for view in (i, j):
        Q = P[view]  # (S,3,4)
        h = Q[:, :, 0] * X[:, 0:1] + Q[:, :, 1] * X[:, 1:2] + Q[:, :, 2] * X[:, 2:3] + Q[:, :, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            du = h[:, 0] / h[:, 2] - uv[view, 0]
            dv = h[:, 1] / h[:, 2] - uv[view, 1]
            err = np.sqrt(du * du + dv * dv)
        errors.append(np.where((h[:, 2] > 0) & np.isfinite(err), err, np.inf))
    return 0.5 * (errors[0] + errors[1]) if reduce == "mean" else np.maximum(*errors)


def pair_reprojection_bound(
    F: np.ndarray, cam: np.ndarray, uv: np.ndarray, i: np.ndarray, j: np.ndarray, reduce: str = "mean"
) -> np.ndarray:
    """(S,) px lower bound of :func:`pair_reprojection_errors` of the pairs (i[s], j[s]).

    F (C,C,3,3): F[a, b] the fundamental matrix with x_b^T F[a, b] x_a = 0 (F[b, a] its
    transpose); cam (N,) each view's camera, uv (N,2) px. Any 3D point (the pair's DLT point
    among them) reprojects to a pair of image points that satisfies the epipolar constraint,
    so the pair's two reprojection errors e_a, e_b move the observations (x_a, x_b) onto the
    constraint surface g = x_b^T F x_a = 0 and sqrt(e_a^2 + e_b^2) >= d, the distance of
    (x_a, x_b) to that surface. g is bilinear, so exactly
    |g| <= |grad g| d + |F_2x2| d^2 / 2 (|F_2x2| the Frobenius norm of the px block, >= its
    spectral norm), which bounds d from below; the mean (max) of e_a, e_b is >= d/2 (d/sqrt 2).
    NaN (no bound) where the geometry is degenerate; a pair behind a camera is unbounded.
    """
    N, C = cam.size, F.shape[0]
    xh = np.concatenate([uv, np.ones((N, 1))], axis=1)
    # every view's epipolar line in every camera, coordinate-first: lines[:, n * C + c]
    lines = np.einsum("ncij,nj->inc", F[cam], xh).reshape(3, N * C)
    ci, cj = cam[i], cam[j]
    la = lines[:, i * C + cj]  # F x_a in b: g and its gradient in x_b
    lb = lines[:2, j * C + ci]  # F^T x_b in a: the gradient in x_a
    g = np.abs(la[0] * uv[j, 0] + la[1] * uv[j, 1] + la[2])
    grad = np.sqrt(la[0] * la[0] + la[1] * la[1] + lb[0] * lb[0] + lb[1] * lb[1])
    cross = np.sqrt((F[..., :2, :2] ** 2).sum((-2, -1)))[ci, cj]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 2.0 * g / (grad + np.sqrt(grad * grad + 2.0 * cross * g))  # root of the bound
    return d * (0.5 if reduce == "mean" else np.sqrt(0.5))
