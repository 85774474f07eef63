"""Per-camera capture time offsets from the people's motion.

Camera c's frame k shows the scene at time (k + delta_c) / fps. For each camera, its 2D tracks
are compared with the 3D tracks triangulated from the other cameras (each moved to the
reference times by its own current offset), interpolated at k + delta: the delta with the
smallest robust reprojection error wins (a scan, then a parabola through the best three
values, then a fine scan), for every camera in turn, twice. Offsets are relative; the median
camera's is taken as 0, so that cameras in sync with most of the rig come out at 0.
"""
from __future__ import annotations

import numpy as np

from .tracks import shift_in_time, triangulate

#: px: a joint's reprojection error counts at most this much (an outlier costs the same anywhere)
TRUNCATE_PX = 6.0


def _project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    h = X @ P[:, :3].T + P[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(h[..., 2:] > 0, h[..., :2] / h[..., 2:], np.nan)


def smooth_tracks(X: np.ndarray, weights=(1.0, 2.0, 3.0, 2.0, 1.0)) -> np.ndarray:
    """(T,F,J,3) tracks averaged over neighbouring frames of the same track (triangular
    window, NaN-aware; NaN where the centre frame is NaN). Linear interpolation between two
    noisy samples has less noise half-way than at a sample, which would pull every offset
    towards half a frame; on smoothed tracks that modulation is small."""
    half = len(weights) // 2
    F = X.shape[1]
    acc = np.zeros_like(X)
    wsum = np.zeros(X.shape[:3] + (1,))
    for k, w in zip(range(-half, half + 1), weights):
        lo, hi = max(0, -k), min(F, F - k)
        part = X[:, lo + k:hi + k]
        ok = np.all(np.isfinite(part), axis=-1, keepdims=True)
        acc[:, lo:hi] += w * np.where(ok, part, 0.0)
        wsum[:, lo:hi] += w * ok
    with np.errstate(invalid="ignore", divide="ignore"):
        out = acc / wsum
    out[~np.all(np.isfinite(X), axis=-1)] = np.nan
    return out


def _interpolated(X: np.ndarray, delta: float) -> np.ndarray:
    """(T,F,J,3) tracks X interpolated at frame k + delta (NaN outside a track)."""
    F = X.shape[1]
    pos = np.arange(F) + delta
    f0 = np.floor(pos).astype(np.int64)
    a = (pos - f0)[None, :, None, None]
    ok = (f0 >= 0) & (f0 + 1 <= F - 1)
    f0c, f1c = np.clip(f0, 0, F - 1), np.clip(f0 + 1, 0, F - 1)
    Xi = (1 - a) * X[:, f0c] + a * X[:, f1c]
    Xi[:, ~ok] = np.nan
    return Xi


def _scan(P_c: np.ndarray, X: np.ndarray, U_c: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """Mean truncated squared error (px^2) of camera c's keypoints U_c (T,F,J,2) against the
    3D tracks X (T,F,J,3) interpolated at frame k + delta, for every delta, over the terms
    defined at all of them (so that the costs compare the same observations)."""
    e2 = np.stack([np.sum((_project(P_c, _interpolated(X, d)) - U_c) ** 2, axis=-1)
                   for d in deltas])
    common = np.all(np.isfinite(e2), axis=0)
    if not common.any():
        return np.full(len(deltas), np.inf)
    return np.mean(np.minimum(e2[:, common], TRUNCATE_PX ** 2), axis=1)


def _best_delta(P_c, X, U_c, centre: float, reach: float) -> float:
    """Scan 0.2 frame steps over centre +- reach, a parabola through the best three, then a
    0.02 frame scan around it."""
    grid = centre + np.arange(-reach, reach + 1e-9, 0.2)
    costs = _scan(P_c, X, U_c, grid)
    if not np.isfinite(costs).any():
        return centre
    k = int(np.argmin(costs))
    best = grid[k]
    if 0 < k < len(grid) - 1:
        c0, c1, c2 = costs[k - 1:k + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best = grid[k] + 0.1 * (c0 - c2) / den
    fine = best + np.arange(-0.1, 0.1001, 0.02)
    fine_costs = _scan(P_c, X, U_c, fine)
    return float(fine[int(np.argmin(fine_costs))]) if np.isfinite(fine_costs).any() else float(best)


def estimate_offsets(P: np.ndarray, U: np.ndarray, max_frames: float, rounds: int = 8,
                     tol: float = 0.01) -> np.ndarray:
    """(C,) offsets in frames of the cameras with projection matrices P (C,3,4) and 2D tracks
    U (C,T,F,J,2), relative to the median camera. Gauss-Seidel: each camera's offset is
    re-estimated against the others moved by their current offsets, until no offset changes
    by more than ``tol`` frames (the first round scans +-max_frames, later ones +-0.5 frame
    around the current value)."""
    C = P.shape[0]
    if C == 2:
        return _two_camera_offset(P, U, max_frames)
    delta = np.zeros(C)
    shifted = U.copy()
    for r in range(rounds):
        before = delta.copy()
        for c in range(C):
            others = [d for d in range(C) if d != c]
            X = smooth_tracks(triangulate(P[others], shifted[others]))
            delta[c] = _best_delta(P[c], X, U[c], delta[c] if r else 0.0,
                                   0.5 if r else max_frames)
            shifted[c] = shift_in_time(U[c], delta[c])
        delta -= np.median(delta)  # offsets are relative: keep the common part at 0
        shifted = np.stack([shift_in_time(U[c], delta[c]) for c in range(C)])
        if np.max(np.abs(delta - before)) < tol:
            break
    return delta


def _two_camera_offset(P: np.ndarray, U: np.ndarray, max_frames: float) -> np.ndarray:
    """Two cameras: the relative offset minimising the triangulation's reprojection error
    (camera 1 moved in time against camera 0), split evenly around 0."""
    grid = np.arange(-max_frames, max_frames + 1e-9, 0.1)

    def cost(d: float) -> float:
        moved = np.stack([U[0], shift_in_time(U[1], d)])
        X = triangulate(P, moved)
        e2 = np.sum((np.stack([_project(P[c], X) for c in range(2)]) - moved) ** 2, axis=-1)
        e2 = e2[np.isfinite(e2)]
        return float(np.mean(np.minimum(e2, TRUNCATE_PX ** 2))) if e2.size else np.inf

    costs = np.array([cost(d) for d in grid])
    d = float(grid[int(np.nanargmin(costs))]) if np.isfinite(costs).any() else 0.0
    fine = d + np.arange(-0.06, 0.0601, 0.01)
    d = float(fine[int(np.nanargmin([cost(x) for x in fine]))])
    return np.array([-d / 2, d / 2])
