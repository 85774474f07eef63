"""Batched similarity Procrustes (Umeyama): rotation, translation and uniform scale.

Shared by the association cost (PA-MPJPE between two detections' 3D keypoints, the fast
``pa_mpjpe_finite`` for validated input) and the evaluation metrics (``pa_mpjpe``, masked). Units are whatever the inputs use (metres here).
"""
from __future__ import annotations

import numpy as np

#: fewer valid joints than this leave the similarity under-determined -> NaN
MIN_JOINTS = 3


def _valid_mask(X: np.ndarray, Y: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    if X.shape != Y.shape or X.ndim < 2 or X.shape[-1] != 3:
        raise ValueError(f"procrustes: X and Y must both be (...,J,3), got {X.shape} and {Y.shape}")
    valid = np.isfinite(X).all(-1) & np.isfinite(Y).all(-1)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        try:
            valid = valid & np.broadcast_to(mask, valid.shape)
        except ValueError:
            raise ValueError(f"procrustes: mask shape {mask.shape} does not match joints "
                             f"{valid.shape}") from None
    return valid


def procrustes_align(X: np.ndarray, Y: np.ndarray, mask: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Align X onto Y with the least-squares similarity s R X + t (batched over leading dims).

    X, Y: (...,J,3); mask: (...,J) bool or None. Joints that are masked out or non-finite in
    either input are ignored when fitting. Returns (aligned X (...,J,3), s (...), R (...,3,3),
    t (...,3)); all NaN where fewer than 3 joints are usable.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    valid = _valid_mask(X, Y, mask)
    w = valid.astype(np.float64)[..., None]
    n = w.sum(-2)  # (...,1)
    ok = n[..., 0] >= MIN_JOINTS
    n_safe = np.maximum(n, 1.0)
    Xz = np.where(valid[..., None], X, 0.0)
    Yz = np.where(valid[..., None], Y, 0.0)
    mu_x = Xz.sum(-2) / n_safe
    mu_y = Yz.sum(-2) / n_safe
    Xc = (Xz - mu_x[..., None, :]) * w
    Yc = (Yz - mu_y[..., None, :]) * w
    var_x = (Xc ** 2).sum((-2, -1)) / n_safe[..., 0]
    cov = np.swapaxes(Yc, -1, -2) @ Xc / n_safe[..., None]
    U, S, Vt = np.linalg.svd(cov)
    # reflection guard: flip the weakest axis when the best orthogonal map is improper
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    R = U @ Vt
    trace = S[..., 0] + S[..., 1] + d * S[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(var_x > 0, trace / var_x, 0.0)
    t = mu_y - s[..., None] * np.einsum("...ij,...j->...i", R, mu_x)
    aligned = s[..., None, None] * (X @ np.swapaxes(R, -1, -2)) + t[..., None, :]
    nan = ~ok
    aligned[nan] = np.nan
    s = np.where(nan, np.nan, s)
    R[nan] = np.nan
    t[nan] = np.nan
    return aligned, s, R, t


def pa_mpjpe(X: np.ndarray, Y: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(...) mean joint distance after similarity-aligning X onto Y (units of Y).

    Joints masked out or non-finite in either input are ignored; NaN where fewer than 3
    joints are usable.
    """
    X = np.asarray(X, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    aligned = procrustes_align(X, Y, mask)[0]
    valid = _valid_mask(X, Y, mask)
    dist = np.linalg.norm(aligned - Y, axis=-1)
    n = valid.sum(-1)
    with np.errstate(invalid="ignore"):
        out = np.where(valid, dist, 0.0).sum(-1) / np.maximum(n, 1)
    return np.where(n >= MIN_JOINTS, out, np.nan)


def pa_mpjpe_finite(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """(S,) PA-MPJPE (units of Y) of X (S,J,3) similarity-aligned onto Y (S,J,3), finite input.

    The same Umeyama alignment as pa_mpjpe (rotation with reflection guard,
    translation, uniform scale) without its mask/NaN handling, which validated detections do
    not need: one stacked SVD of the 3x3 covariances. Fewer than 3 joints do not fix a
    similarity (any two point pairs align exactly), so the cost is NaN (= gated) then.
    """
    if X.shape[1] < 3:
        return np.full(X.shape[0], np.nan)
    Xc = X - X.mean(axis=1, keepdims=True)
    Yc = Y - Y.mean(axis=1, keepdims=True)
    U, S, Vt = np.linalg.svd(np.matmul(Yc.transpose(0, 2, 1), Xc))
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    d[d == 0] = 1.0
    U[:, :, 2] *= d[:, None]
    R = np.matmul(U, Vt)
    var = np.einsum("sjk,sjk->s", Xc, Xc)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(var > 0, (S[:, 0] + S[:, 1] + d * S[:, 2]) / var, 0.0)
    aligned = scale[:, None, None] * np.matmul(Xc, R.transpose(0, 2, 1))
    return np.linalg.norm(aligned - Yc, axis=2).mean(axis=1)
