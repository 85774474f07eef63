"""MAEM stage 3: per-keypoint RANSAC over view-pair DLT hypotheses, then weighted DLT.

For every cluster and keypoint j: each pair of member views gives a DLT hypothesis;
a view is an inlier of a hypothesis when its reprojection error (rectified pinhole px,
through ``Camera.P``) is below ``tau_kps``; the best hypothesis has the most inliers
(tie: the lower mean inlier error); the keypoint is re-triangulated from all inliers of
the best hypothesis with a detection-score-weighted DLT. Fewer than ``min_views`` usable
inlier views (non-finite 2D input is unusable) -> NaN.

Everything is batched: all clusters, view pairs and joints are solved in array
operations, with the 3x3 normal equations of the DLT solved in closed form (numpy's
per-matrix SVD/LAPACK calls cost ~2 us each, far too slow for ~10^4 small systems).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from .camera import Rig
from .detections import FrameDetections

if TYPE_CHECKING:  # only the .members attribute is used; avoids a hard import cycle
    from .association import Cluster

#: a view whose detection score is 0 still counts as a view, with this tiny DLT weight
_MIN_WEIGHT = 1e-3
#: relative determinant below which the normal equations are treated as singular
_SINGULAR = 1e-13


@dataclass
class TriangulationParams:
    """tau_kps: keypoint inlier threshold (rectified px); min_views: inlier views per keypoint."""

    tau_kps: float = 20.0
    min_views: int = 2

    def __post_init__(self) -> None:
        self.tau_kps = float(self.tau_kps)
        if not np.isfinite(self.tau_kps) or self.tau_kps <= 0:
            raise ValueError(f"tau_kps: must be a positive number of px, got {self.tau_kps}")
        if int(self.min_views) != self.min_views or self.min_views < 2:
            raise ValueError(f"min_views: must be an integer >= 2, got {self.min_views}")
        self.min_views = int(self.min_views)

    @classmethod
    def from_mapping(cls, d: Mapping[str, Any]) -> "TriangulationParams":
        """Take the known keys of a params dict (others, e.g. frame_id, are ignored)."""
        kwargs = {k: d[k] for k in ("tau_kps", "min_views") if k in d}
        for k, v in kwargs.items():
            if isinstance(v, (bool, str)) or not isinstance(v, (int, float, np.number)):
                raise ValueError(f"{k}: expected a number, got {v!r}")
        return cls(**kwargs)


@dataclass
class Poses:
    """Triangulated people of one frame, in cluster order.

    joints (P,J,3) world metres (NaN = missing); views (P,) member views per cluster;
    inliers (P,J) inlier views used per joint (0 where NaN); scores (P,) mean detection
    score of the members.
    """

    joints: np.ndarray
    views: np.ndarray
    inliers: np.ndarray
    scores: np.ndarray

    def __len__(self) -> int:
        return int(self.joints.shape[0])


# ---------------------------------------------------------------------------------------
# DLT
# ---------------------------------------------------------------------------------------
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
    pair hypotheses and the final fit reuse one computation. Unusable views give zeros.
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
    n00, n01, n02, n11, n12, n22 = E[0], E[1], E[2], E[3], E[4], E[5]
    r0, r1, r2 = -E[6], -E[7], -E[8]
    c00 = n11 * n22 - n12 * n12
    c01 = n02 * n12 - n01 * n22
    c02 = n01 * n12 - n02 * n11
    c11 = n00 * n22 - n02 * n02
    c12 = n01 * n02 - n00 * n12
    c22 = n00 * n11 - n01 * n01
    det = n00 * c00 + n01 * c01 + n02 * c02
    singular = ~(np.abs(det) > _SINGULAR * (n00 + n11 + n22) ** 3)
    inv_det = np.where(singular, np.nan, 1.0 / np.where(singular, 1.0, det))
    X = np.empty(E.shape[1:] + (3,))
    X[..., 0] = (c00 * r0 + c01 * r1 + c02 * r2) * inv_det
    X[..., 1] = (c01 * r0 + c11 * r1 + c12 * r2) * inv_det
    X[..., 2] = (c02 * r0 + c12 * r1 + c22 * r2) * inv_det
    return X


def reprojection_error(P: np.ndarray, X: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(C,M,Q,J) px errors of hypotheses X (C,Q,J,3) in views P (C,M,3,4) against uv (C,M,J,2).

    Inf for points behind the camera (depth <= 0) or non-finite input.
    """
    C, M = P.shape[:2]
    Q, J = X.shape[1:3]
    # one batched GEMM per cluster for all projections: (C, M*3, 3) @ (C, 3, Q*J)
    h = np.matmul(P[..., :3].reshape(C, M * 3, 3), X.reshape(C, Q * J, 3).transpose(0, 2, 1))
    h = h.reshape(C, M, 3, Q, J) + P[:, :, :, 3, None, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = 1.0 / h[:, :, 2]
        du = h[:, :, 0] * inv_z - uv[:, :, None, :, 0]
        dv = h[:, :, 1] * inv_z - uv[:, :, None, :, 1]
        err = np.sqrt(du * du + dv * dv)
    return np.where((h[:, :, 2] > 0) & np.isfinite(err), err, np.inf)


# ---------------------------------------------------------------------------------------
# stage 3
# ---------------------------------------------------------------------------------------
def triangulate(rig: Rig, frames: Mapping[str, FrameDetections], clusters: Sequence["Cluster"],
                params: TriangulationParams | None = None) -> Poses:
    """Triangulate every cluster (members = (camera index in rig order, detection index))."""
    params = params or TriangulationParams()
    J = _num_joints(frames)
    C = len(clusters)
    if C == 0:
        return Poses(np.zeros((0, J, 3)), np.zeros(0, np.int64), np.zeros((0, J), np.int64),
                     np.zeros(0))
    P, uv, score, present = _gather(rig, frames, clusters, J)  # (C,M,3,4) (C,M,J,2) (C,M) (C,M)
    M = P.shape[1]
    usable = present[:, :, None] & np.isfinite(uv).all(-1)  # (C,M,J)
    weight = np.maximum(score, _MIN_WEIGHT)

    E = normal_entries(P[:, :, None], uv, usable)  # (9,C,M,J)
    ia, ib = np.triu_indices(M, 1)  # view pairs (Q,)
    hyp = solve_normal(E[:, :, ia] + E[:, :, ib])  # (C,Q,J,3), unweighted two-view DLT
    hyp[~(usable[:, ia] & usable[:, ib])] = np.nan
    # reprojection of every hypothesis into every member view: (C,M,Q,J)
    err = reprojection_error(P, hyp, uv)
    err = np.where(usable[:, :, None], err, np.inf)
    inlier = err < params.tau_kps
    count = inlier.sum(1)  # (C,Q,J)
    mean_err = np.where(inlier, err, 0.0).sum(1) / np.maximum(count, 1)
    # most inliers first; mean_err / (2 tau) < 0.5 breaks ties without crossing counts
    key = np.where(np.isfinite(hyp[..., 0]), count - mean_err / (2.0 * params.tau_kps), -1.0)
    best = np.argmax(key, axis=1)  # (C,J)
    best_inl = np.take_along_axis(inlier, best[:, None, None, :], axis=2)[:, :, 0]  # (C,M,J)
    n_inl = best_inl.sum(1)
    ok = n_inl >= params.min_views

    w2 = np.where(best_inl, weight[:, :, None] ** 2, 0.0)  # (C,M,J)
    X = solve_normal((E * w2).sum(2))  # (C,J,3) score-weighted DLT
    X = np.where(ok[..., None], X, np.nan)
    n_inl = np.where(np.isfinite(X).all(-1), n_inl, 0)
    mean_score = (score * present).sum(1) / np.maximum(present.sum(1), 1)
    return Poses(X, present.sum(1).astype(np.int64), n_inl.astype(np.int64), mean_score)


def _num_joints(frames: Mapping[str, FrameDetections]) -> int:
    counts = {name: f.kpts2d.shape[1] for name, f in frames.items()
              if f.kpts2d.ndim == 3 and f.kpts2d.shape[0] > 0}
    if len(set(counts.values())) > 1:
        raise ValueError(f"frames: keypoint count differs between cameras: {counts}")
    if counts:
        return next(iter(counts.values()))
    return max((f.kpts2d.shape[1] for f in frames.values() if f.kpts2d.ndim == 3), default=0)


def _gather(rig: Rig, frames: Mapping[str, FrameDetections], clusters: Sequence["Cluster"], J: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pad clusters to M views: P (C,M,3,4), uv (C,M,J,2), score (C,M), present (C,M)."""
    members = [np.asarray(c.members, dtype=np.int64).reshape(-1, 2) for c in clusters]
    C, M = len(members), max(2, max(m.shape[0] for m in members))  # >= 1 view pair
    cam = np.zeros((C, M), np.int64)
    det = np.zeros((C, M), np.int64)
    present = np.zeros((C, M), bool)
    for k, m in enumerate(members):  # one row per cluster, not per joint or vertex
        cam[k, :len(m)], det[k, :len(m)], present[k, :len(m)] = m[:, 0], m[:, 1], True

    names = rig.names
    if present.any() and (cam[present].min() < 0 or cam[present].max() >= len(names)):
        raise ValueError(f"clusters: members: camera index outside the rig's 0..{len(names) - 1}")
    # flatten every used camera's detections into one table, offset per camera
    Ps = np.stack([c.P for c in rig.cameras])
    offsets = np.zeros(len(names), np.int64)
    kp, sc, sizes = [], [], np.zeros(len(names), np.int64)
    total = 0
    for ci in np.unique(cam[present]):
        name = names[ci]
        if name not in frames:
            raise ValueError(f"clusters: members: camera {name!r} has no detections in this frame")
        f = frames[name]
        offsets[ci], sizes[ci] = total, f.n
        total += f.n
        kp.append(f.kpts2d.reshape(f.n, J, 2))
        sc.append(f.scores)
    bad = present & ((det < 0) | (det >= sizes[cam]))
    if bad.any():
        c, m = np.argwhere(bad)[0]
        raise ValueError(f"clusters: members: detection {det[c, m]} out of range for camera "
                         f"{names[cam[c, m]]!r} ({sizes[cam[c, m]]} detections) in cluster {c}")
    kp_all = np.concatenate(kp) if kp else np.zeros((0, J, 2))
    sc_all = np.concatenate(sc) if sc else np.zeros(0)
    row = np.where(present, offsets[cam] + det, 0)
    uv = np.where(present[..., None, None], kp_all[row] if total else np.nan, np.nan)
    score = np.where(present, sc_all[row] if total else 0.0, 0.0)
    return Ps[cam], uv, score, present
