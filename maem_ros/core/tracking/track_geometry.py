"""Batched multi-view geometry of the track stage (core.tracking.temporal): projections of
predicted joints, NaN-aware medians, the triangulation and verification of candidate
clusters padded to M members, and the one-view update's ray point (rectified px, world m)."""

from __future__ import annotations

import numpy as np

from maem_ros.core.geometry.multiview import dlt


def project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project X (...,3) with P (...,3,4) broadcast: (uv (...,2) px, depth (...)); NaN behind."""
    h = np.einsum("...ij,...j->...i", P[..., :3], X) + P[..., 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        uv = h[..., :2] / h[..., 2:3]
    return np.where((h[..., 2:3] > 0), uv, np.nan), h[..., 2]


def median_depth(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(T,) median depth (m) of the points X (T,J,3) in the camera P (3,4); NaN if none in front."""
    _, z = project(P, X)
    return nanmedian(np.where(z > 0, z, np.nan))


def nanmedian(a: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN; NaN where all are NaN. One sort (NaN sorts last)
    instead of np.nanmedian, whose masked-array path costs ~2 ms per call on small arrays."""
    srt = np.sort(a, axis=-1)
    n = np.isfinite(a).sum(-1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[..., None], -1)[..., 0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def triangulate_members(P: np.ndarray, uv: np.ndarray, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joints X (T,J,3) from members padded to M views and each member's median reprojection
    error (T,M) px (inf where absent or not reprojectable).

    P (T,M,3,4), uv (T,M,J,2), present (T,M).
    """
    w = present.astype(np.float64)  # (T,M)
    Pj = np.broadcast_to(P[:, None], (P.shape[0], uv.shape[2]) + P.shape[1:])  # (T,J,M,3,4)
    X = dlt(Pj, uv.transpose(0, 2, 1, 3), np.broadcast_to(w[:, None], Pj.shape[:3]))
    proj, _ = project(P[:, :, None], X[:, None])  # (T,M,J,2)
    with np.errstate(invalid="ignore"):
        err = np.linalg.norm(proj - uv, axis=-1)
    err = np.where(np.isfinite(err), err, np.nan)
    med = nanmedian(err)
    return X, np.where(present & np.isfinite(med), med, np.inf)


def verify_clusters(
    P: np.ndarray, uv: np.ndarray, present: np.ndarray, passes: np.ndarray, tau_px: float, min_support: float
) -> tuple[np.ndarray, np.ndarray]:
    """Geometric verification of clusters padded to M members, as in the consistent clustering:
    every member must pass the pair gates with at least ``min_support`` of the other members
    (passes (T,M,M) bool) and reproject under tau_px (median over the body joints triangulated
    from all kept members). The worst member (least support, then largest error) is dropped
    until all pass or fewer than 2 remain. Returns (kept (T,M), joints (T,J,3) of the kept
    members, NaN where fewer than 2 are kept)."""
    keep = present.copy()
    for _ in range(max(present.shape[1] - 1, 1)):  # at most M-1 drops, batched over clusters
        X, err = triangulate_members(P, uv, keep)
        others = np.maximum(keep.sum(1, keepdims=True) - 1, 1)
        support = (passes & keep[:, None, :]).sum(2) / others  # (T,M)
        bad = keep & ((err >= tau_px) | (support < min_support))
        todo = bad.any(1) & (keep.sum(1) >= 2)
        if not todo.any():
            break
        # least support first; the error (px, < 1e6) breaks ties
        badness = np.where(keep, (1.0 - support) * 1e6 + np.minimum(err, 1e6 - 1), -1.0)
        worst = np.argmax(badness, axis=1)
        keep[np.flatnonzero(todo), worst[todo]] = False
    X[keep.sum(1) < 2] = np.nan
    return keep, X


def rays_nearest(cam_P: np.ndarray, center: np.ndarray, uv: np.ndarray, X_pred: np.ndarray) -> np.ndarray:
    """(J,3) points on the back-projected rays of uv (J,2) nearest to X_pred (J,3): one view
    plus the prediction (the view fixes the direction, the prediction the depth)."""
    M_inv = np.linalg.inv(cam_P[:, :3])
    d = (M_inv @ np.concatenate([uv, np.ones((len(uv), 1))], axis=1).T).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    s = np.einsum("jk,jk->j", X_pred - center, d)
    return center + s[:, None] * d


def mean_distance(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(G,K) mean distance (m) over joints finite in both of A (G,J,3) and B (K,J,3)."""
    both = np.isfinite(A).all(-1)[:, None] & np.isfinite(B).all(-1)[None]
    with np.errstate(invalid="ignore"):
        d = np.linalg.norm(A[:, None] - B[None], axis=-1)
    n = both.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.where(both, d, 0.0).sum(-1) / n, np.inf)
