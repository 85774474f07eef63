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
TRUNCATE_PX = 20.0


def _project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    h = X @ P[:, :3].T + P[:, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(h[..., 2:] > 0, h[..., :2] / h[..., 2:], np.nan)


def _cost(P_c: np.ndarray, X: np.ndarray, U_c: np.ndarray, delta: float) -> float:
    """Mean truncated squared error of camera c's keypoints U_c (T,F,J,2) against the 3D
    tracks X (T,F,J,3) interpolated at frame k + delta."""
    F = X.shape[1]
    pos = np.arange(F) + delta
    f0 = np.floor(pos).astype(np.int64)
    a = (pos - f0)[None, :, None, None]
    ok = (f0 >= 0) & (f0 + 1 <= F - 1)
    f0c, f1c = np.clip(f0, 0, F - 1), np.clip(f0 + 1, 0, F - 1)
    Xi = (1 - a) * X[:, f0c] + a * X[:, f1c]
    Xi[:, ~ok] = np.nan
    e2 = np.sum((_project(P_c, Xi) - U_c) ** 2, axis=-1)
    e2 = e2[np.isfinite(e2)]
    if e2.size == 0:
        return np.inf
    return float(np.mean(np.minimum(e2, TRUNCATE_PX ** 2)))


def _best_delta(P_c, X, U_c, max_frames: float) -> float:
    grid = np.arange(-max_frames, max_frames + 1e-9, 0.1)
    costs = np.array([_cost(P_c, X, U_c, d) for d in grid])
    if not np.isfinite(costs).any():
        return 0.0
    k = int(np.nanargmin(costs))
    best = grid[k]
    if 0 < k < len(grid) - 1 and np.all(np.isfinite(costs[k - 1:k + 2])):
        c0, c1, c2 = costs[k - 1:k + 2]
        den = c0 - 2 * c1 + c2
        if den > 0:
            best = grid[k] + 0.05 * (c0 - c2) / den
    fine = best + np.arange(-0.06, 0.0601, 0.01)
    fine_costs = np.array([_cost(P_c, X, U_c, d) for d in fine])
    return float(fine[int(np.nanargmin(fine_costs))])


def estimate_offsets(P: np.ndarray, U: np.ndarray, max_frames: float, rounds: int = 2) -> np.ndarray:
    """(C,) offsets in frames of the cameras with projection matrices P (C,3,4) and 2D tracks
    U (C,T,F,J,2), relative to the median camera."""
    C = P.shape[0]
    delta = np.zeros(C)
    for _ in range(rounds):
        shifted = np.stack([shift_in_time(U[c], delta[c]) for c in range(C)])
        for c in range(C):
            others = [d for d in range(C) if d != c]
            if len(others) < 2:
                continue  # a 2-camera rig: c's motion is compared with one camera's below
            X = triangulate(P[others], shifted[others])
            delta[c] = _best_delta(P[c], X, U[c], max_frames)
        delta -= np.median(delta)
    if C == 2:
        delta = _two_camera_offset(P, U, max_frames)
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
