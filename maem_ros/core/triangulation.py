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
from .geometry import dlt, normal_entries, reprojection_error, solve_normal  # noqa: F401 (dlt re-exported)

if TYPE_CHECKING:  # only the .members attribute is used; avoids a hard import cycle
    from .association import Cluster

#: a view whose detection score is 0 still counts as a view, with this tiny DLT weight
_MIN_WEIGHT = 1e-3


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
