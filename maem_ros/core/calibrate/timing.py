"""Per-camera capture time offsets from the people's motion.

Camera c's frame k shows the scene at time (k + delta_c) / fps. For each camera, its 2D tracks
are compared with the 3D tracks triangulated from the other cameras (each moved to the
reference times by its own current offset), smoothed and evaluated at k + delta by a narrow
Gaussian kernel in continuous time (kernel_tracks): the delta with the smallest robust
reprojection error wins (a scan, then a parabola through the best three values, then a fine
scan), for every camera in turn, until the offsets settle. Offsets are relative; the median
camera's is taken as 0, so that cameras in sync with most of the rig come out at 0.
"""
from __future__ import annotations

import numpy as np

from .tracks import shift_in_time, triangulate

#: px: a joint's reprojection error counts at most this much (an outlier costs the same anywhere)
TRUNCATE_PX = 6.0
#: frames: sd of the Gaussian the 3D tracks are smoothed with in continuous time (kernel_tracks)
SMOOTH_SIGMA = 0.7
#: the kernel is cut at this many sd (the weight there is 1e-3 of the centre's)
KERNEL_REACH = 3.0


def _project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    h = X @ P[:, :3].T + P[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(h[..., 2:] > 0, h[..., :2] / h[..., 2:], np.nan)


def kernel_tracks(X: np.ndarray, where: tuple[np.ndarray, ...], deltas: np.ndarray,
                  sigma: float = SMOOTH_SIGMA) -> np.ndarray:
    """(D,N,3) tracks X (T,F,J,3) smoothed by a Gaussian kernel of ``sigma`` frames and
    evaluated at the continuous frame positions k + delta of the N entries ``where`` (3
    arrays: track, frame k, joint), for each of the D ``deltas`` (NaN-aware; NaN where the
    track lacks either frame around k + delta).

    Why a kernel in continuous time: linear interpolation of noisy samples has half the noise
    variance half-way between two frames than at a frame, and smoothing at the frames first
    (then interpolating) keeps part of that modulation, which pulls every offset towards half
    a frame; a Gaussian wider than about half a frame has the same noise at any sub-frame
    position. A narrow one: wider kernels flatten fast limb motion, and that bias (with
    occluded, broken tracks) is larger than the noise they remove. The kernel is linear in X:
    the samples around every entry are gathered once and all deltas weigh them in one product
    (only the observed entries are evaluated)."""
    F = X.shape[1]
    t, k, j = where
    half = int(np.ceil(KERNEL_REACH * sigma))
    base = np.floor(deltas).astype(np.int64)
    lo, hi = int(base.min()) - half, int(base.max()) + half + 1
    ms = np.arange(lo, hi + 1)
    frame = k[:, None] + ms[None]  # (N,M) the samples every delta may weigh
    inside = (frame >= 0) & (frame < F)
    G = X[t[:, None], np.clip(frame, 0, F - 1), j[:, None]]
    ok = inside & np.all(np.isfinite(G), axis=-1)
    G = np.where(ok[..., None], G, 0.0)
    W = np.exp(-0.5 * ((ms[None] - deltas[:, None]) / sigma) ** 2)  # (D,M)
    W[(ms[None] < base[:, None] - half) | (ms[None] > base[:, None] + half + 1)] = 0.0
    num = W @ G.transpose(1, 0, 2).reshape(len(ms), -1)  # (D,N*3)
    den = W @ ok.T.astype(float)  # (D,N)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num.reshape(len(deltas), -1, 3) / den[..., None]
    col = base - lo  # column of frame floor(k + delta)
    both = ok[:, col].T & ok[:, col + 1].T  # (D,N)
    out[~both] = np.nan
    return out


def _scan(P_c: np.ndarray, X: np.ndarray, U_c: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """Mean truncated squared error (px^2) of camera c's keypoints U_c (T,F,J,2) against the
    3D tracks X (T,F,J,3) smoothed and evaluated at frame k + delta (kernel_tracks), for every
    delta, over the terms defined at all of them (so that the costs compare the same
    observations)."""
    seen = np.all(np.isfinite(U_c), axis=-1)
    where = np.nonzero(seen)
    e2 = np.sum((_project(P_c, kernel_tracks(X, where, deltas)) - U_c[seen]) ** 2, axis=-1)
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
                     tol: float = 0.01, start: np.ndarray | None = None) -> np.ndarray:
    """(C,) offsets in frames of the cameras with projection matrices P (C,3,4) and 2D tracks
    U (C,T,F,J,2), relative to the median camera. Gauss-Seidel: each camera's offset is
    re-estimated against the others moved by their current offsets, until no offset changes
    by more than ``tol`` frames (the first round scans +-max_frames, later ones +-0.5 frame
    around the current value). ``start`` (C,) frames: offsets already close (from a previous
    rig), searched +-0.5 frame from the first round on: no full scan."""
    C = P.shape[0]
    if C == 2:
        return _two_camera_offset(P, U, max_frames)
    warm = start is not None
    delta = np.zeros(C) if start is None else np.asarray(start, float).copy()
    shifted = np.stack([shift_in_time(U[c], delta[c]) for c in range(C)]) if warm else U.copy()
    for r in range(rounds):
        before = delta.copy()
        for c in range(C):
            others = [d for d in range(C) if d != c]
            X = triangulate(P[others], shifted[others])
            near = bool(r or warm)
            delta[c] = _best_delta(P[c], X, U[c], delta[c] if near else 0.0,
                                   0.5 if near else max_frames)
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
