"""MAEM stage 3: per-keypoint RANSAC over view-pair DLT hypotheses, then weighted DLT.

For every cluster and keypoint j: each pair of member views gives a DLT hypothesis;
a view is an inlier of a hypothesis when its reprojection error (rectified pinhole px,
through ``Camera.P``) is below ``tau_kps``; the best hypothesis has the most inliers
(tie: the lower mean inlier error); the keypoint is re-triangulated from all inliers of
the best hypothesis with a detection-score-weighted DLT. Fewer than ``min_views`` usable
inlier views (non-finite 2D input is unusable) -> NaN.

Beyond the paper (``left_right``, default off): monocular estimators such as BlazePose label a
person seen from behind as seen from the front, so one view's left and right joints are swapped.
Before the RANSAC, each cluster picks the left/right labelling of its views (one flip bit per
view, every combination tried) that minimises the summed median two-view reprojection residual
over all its view pairs; of two equally good labellings (all bits inverted) the one that flips
the lower-scored views is kept.

Everything is batched: all clusters, view pairs and joints are solved in array
operations, with the 3x3 normal equations of the DLT solved in closed form (numpy's
per-matrix SVD/LAPACK calls have a fixed cost each, far too much for ~10^4 small systems).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from maem_ros.core.detections import Cluster, FrameDetections
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.geometry.multiview import normal_entries, reprojection_error, solve_normal
from maem_ros.core.paramspec import Params, param
from maem_ros.core.triangulation.ransac_kernel import BACKENDS, ransac_keypoints, use_numba
from maem_ros.core.triangulation.uncertainty import joint_covariance, joint_std, pose_scores

#: a view whose detection score is 0 still counts as a view, with this tiny DLT weight
_MIN_WEIGHT = 1e-3


@dataclass
class TriangulationParams(Params):
    """Per-keypoint RANSAC triangulation thresholds (one field = one parameter of the
    triangulation node, see core/paramspec.py)."""

    tau_kps: float = param(
        20.0, "px, keypoint inlier threshold (rectified image)", minimum=0.0, exclusive_minimum=True
    )
    min_views: int = param(2, "inlier views needed per keypoint", minimum=2)
    left_right: bool = param(
        False,
        "relabel each cluster's views left/right consistently before "
        "the RANSAC (monocular left/right swaps; off = the paper)",
    )
    tau_member: float = param(
        0.0,
        "px, from three views on leave out (and re-triangulate "
        "without) each member whose median reprojection error over "
        "the triangulated joints is >= this: a wrong detection as a "
        "whole, e.g. a body mixed from two people (0 = off, the paper)",
        minimum=0.0,
    )
    ransac_backend: str = param(
        "auto",
        "RANSAC kernel (auto = numba when installed, else the numpy path; the same results)",
        choices=BACKENDS,
    )
    pose_score: str = param(
        "uncertainty",
        "a pose's score: uncertainty (the members' mean "
        "detection score times a confidence from the joints' "
        "predicted error, core/triangulation/uncertainty.py) "
        "or paper (mean detection score of the members)",
        choices=("uncertainty", "paper"),
    )
    noise_prior_px: float = param(
        2.0, "px, prior keypoint noise of the joint covariance", minimum=0.0, exclusive_minimum=True
    )
    noise_prior_dof: float = param(
        2.0, "weight of noise_prior_px in residual degrees of freedom", minimum=0.0
    )
    score_ref_m: float = param(
        0.05, "m, predicted pose error that halves the uncertainty score", minimum=0.0, exclusive_minimum=True
    )


@dataclass
class Poses:
    """Triangulated people of one frame, in cluster order.

    joints (P,J,3) world metres (NaN = missing); views (P,) member views per cluster;
    inliers (P,J) inlier views used per joint (0 where NaN); scores (P,) mean detection
    score of the members; mirrored (P,M) True where member m's left/right labels were swapped
    (``left_right``; member order of the cluster, M = most members of any cluster), else None;
    rejected (P,M) True where member m was left out as a whole (``tau_member``), else None;
    joint_std (P,J) per-joint standard deviation, m, and joint_cov (P,J,3,3) the joints'
    covariance, m^2 (core/triangulation/uncertainty.py; NaN where the joint is missing);
    detection_scores (P,) the members' mean detection score (the paper's score). ``views`` counts
    the members used (rejected ones excluded). ``scores`` follow ``pose_score``.
    """

    joints: np.ndarray
    views: np.ndarray
    inliers: np.ndarray
    scores: np.ndarray
    mirrored: np.ndarray | None = None
    rejected: np.ndarray | None = None
    joint_std: np.ndarray | None = None
    joint_cov: np.ndarray | None = None
    detection_scores: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.joints.shape[0])


# ---------------------------------------------------------------------------------------
# stage 3
# ---------------------------------------------------------------------------------------
def triangulate(
    rig: Rig,
    frames: Mapping[str, FrameDetections],
    clusters: Sequence[Cluster],
    params: TriangulationParams | None = None,
) -> Poses:
    """Triangulate every cluster (members = (camera index in rig order, detection index))."""
    J = _num_joints(frames)
    if not clusters:
        return triangulate_members(
            _rig_P(rig),
            *pad_members(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, J, 2)), np.zeros(0)),
            params,
        )
    members = [np.asarray(c.members, dtype=np.int64).reshape(-1, 2) for c in clusters]
    allm = np.concatenate(members)
    names = rig.names
    if allm.size and (allm[:, 0].min() < 0 or allm[:, 0].max() >= len(names)):
        raise ValueError(f"clusters: members: camera index outside the rig's 0..{len(names) - 1}")
    by_index = {}
    for ci in np.unique(allm[:, 0]):
        if names[ci] not in frames:
            raise ValueError(f"clusters: members: camera {names[ci]!r} has no detections in this frame")
        by_index[int(ci)] = frames[names[ci]]
    sizes = np.zeros(len(names), np.int64)
    for ci, fd in by_index.items():
        sizes[ci] = fd.n
    bad = (allm[:, 1] < 0) | (allm[:, 1] >= sizes[allm[:, 0]])
    if bad.any():
        c, d = allm[int(np.argmax(bad))]
        raise ValueError(
            f"clusters: members: detection {d} out of range for camera {names[c]!r} ({sizes[c]} detections)"
        )
    kpts2d, score = np.empty((len(allm), J, 2)), np.empty(len(allm))
    for ci, fd in by_index.items():  # one gather per camera of the members' rows
        rows = np.flatnonzero(allm[:, 0] == ci)
        kpts2d[rows] = fd.kpts2d[allm[rows, 1]]
        score[rows] = fd.scores[allm[rows, 1]]
    which = np.repeat(np.arange(len(members)), [len(m) for m in members])
    return triangulate_members(_rig_P(rig), *pad_members(which, allm[:, 0], kpts2d, score), params)


def _rig_P(rig: Rig) -> np.ndarray:
    return np.stack([c.P for c in rig.cameras]) if len(rig) else np.zeros((0, 3, 4))


def pad_members(
    cluster: np.ndarray, camera: np.ndarray, kpts2d: np.ndarray, score: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Member rows (R,) -> dense padded arrays, clusters in order of first appearance.

    cluster (R,) id of each row's cluster; camera (R,) rig index; kpts2d (R,J,2) rectified px;
    score (R,). Returns cam (C,M), uv (C,M,J,2) (NaN padding), score (C,M), present (C,M)
    with M >= 2 (one view pair at least).
    """
    J = kpts2d.shape[1] if kpts2d.ndim == 3 else 0
    _, first, inverse, counts = np.unique(cluster, return_index=True, return_inverse=True, return_counts=True)
    rank = np.argsort(np.argsort(first, kind="stable"), kind="stable")  # order of appearance
    k = rank[inverse] if cluster.size else np.zeros(0, np.int64)
    C, M = first.size, max(2, int(counts.max(initial=0)))
    order = np.argsort(k, kind="stable")
    slot = np.empty(cluster.size, np.int64)
    starts = np.concatenate([[0], np.cumsum(np.bincount(k, minlength=C))[:-1]]) if C else np.zeros(0, int)
    slot[order] = np.arange(cluster.size) - starts[k[order]]
    cam = np.zeros((C, M), np.int64)
    uv = np.full((C, M, J, 2), np.nan)
    sc = np.zeros((C, M))
    present = np.zeros((C, M), bool)
    cam[k, slot], uv[k, slot], sc[k, slot], present[k, slot] = camera, kpts2d, score, True
    return cam, uv, sc, present


def triangulate_members(
    P_rig: np.ndarray,
    cam: np.ndarray,
    uv: np.ndarray,
    score: np.ndarray,
    present: np.ndarray,
    params: TriangulationParams | None = None,
) -> Poses:
    """Stage 3 on dense member arrays (see pad_members): P_rig (K,3,4) rectified world->px of
    the rig's cameras; cam (C,M) rig index per member; uv (C,M,J,2) px; score (C,M);
    present (C,M). Returns Poses in cluster order."""
    params = params or TriangulationParams()
    C, M = present.shape
    J = uv.shape[2]
    if C == 0:
        return Poses(
            np.zeros((0, J, 3)),
            np.zeros(0, np.int64),
            np.zeros((0, J), np.int64),
            np.zeros(0),
            joint_std=np.zeros((0, J)),
            joint_cov=np.zeros((0, J, 3, 3)),
            detection_scores=np.zeros(0),
        )
    poses = _ransac_members(P_rig, cam, uv, score, present, params)
    if params.tau_member > 0:
        rejected = _rejected_members(P_rig[cam], uv, present, poses, params.tau_member)
        if rejected.any():
            kept = _ransac_members(P_rig, cam, uv, score, present & ~rejected, params)
            kept.rejected = rejected
            return kept
        poses.rejected = rejected
    return poses


def _rejected_members(
    P: np.ndarray, uv: np.ndarray, present: np.ndarray, poses: Poses, tau: float
) -> np.ndarray:
    """(C,M) members whose median reprojection error (px) over the cluster's triangulated joints
    is >= tau, in clusters that keep two members or more without them (else none)."""
    if poses.mirrored is not None:  # compare each view with the labels the RANSAC used
        J = uv.shape[2]
        uv = np.where(poses.mirrored[:, :, None, None], uv[:, :, mirror_permutation(J)], uv)
    err = reprojection_error(P, poses.joints[:, None], uv)[:, :, 0]  # (C,M,J), inf if unusable
    err = np.where(np.isfinite(err), err, np.nan)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a member with no usable joint
        med = np.nanmedian(err, axis=-1)
    bad = present & (med >= tau)
    enough = (present & ~bad).sum(1) >= 2
    return bad & enough[:, None]


def _ransac_members(
    P_rig: np.ndarray,
    cam: np.ndarray,
    uv: np.ndarray,
    score: np.ndarray,
    present: np.ndarray,
    params: TriangulationParams,
) -> Poses:
    """The per-keypoint RANSAC of triangulate_members on the present members."""
    J = uv.shape[2]
    P = P_rig[cam]  # (C,M,3,4)
    mirrored = None
    if params.left_right:
        mirrored = consistent_left_right(P, uv, score, present, mirror_permutation(J))
        uv = np.where(mirrored[:, :, None, None], uv[:, :, mirror_permutation(J)], uv)
    usable = present[:, :, None] & np.isfinite(uv[..., 0]) & np.isfinite(uv[..., 1])  # (C,M,J)
    weight = np.maximum(score, _MIN_WEIGHT)
    if use_numba(params.ransac_backend):
        X, n_inl = ransac_keypoints(P, uv, usable, weight, params.tau_kps, params.min_views)
    else:
        X, n_inl = _ransac_numpy(P, uv, usable, weight, params.tau_kps, params.min_views)
    cov, _ = joint_covariance(P, X, uv, usable, params.tau_kps, params.noise_prior_px, params.noise_prior_dof)
    std = joint_std(cov)
    detection_scores = (score * present).sum(1) / np.maximum(present.sum(1), 1)
    return Poses(
        X,
        present.sum(1).astype(np.int64),
        n_inl.astype(np.int64),
        pose_scores(detection_scores, std, params.pose_score, params.score_ref_m),
        mirrored,
        joint_std=std,
        joint_cov=cov,
        detection_scores=detection_scores,
    )


def _ransac_numpy(
    P: np.ndarray, uv: np.ndarray, usable: np.ndarray, weight: np.ndarray, tau: float, min_views: int
) -> tuple[np.ndarray, np.ndarray]:
    """The numpy path of triangulation_kernel.ransac_keypoints (same arguments and results):
    every hypothesis of every view pair reprojected into every view as (C,M,Q,J) arrays."""
    M = usable.shape[1]
    E = normal_entries(P[:, :, None], uv, usable)  # (9,C,M,J)
    ia, ib = np.triu_indices(M, 1)  # view pairs (Q,)
    hyp = solve_normal(E[:, :, ia] + E[:, :, ib])  # (C,Q,J,3), unweighted two-view DLT
    hyp[~(usable[:, ia] & usable[:, ib])] = np.nan
    # reprojection of every hypothesis into every member view: (C,M,Q,J)
    err = reprojection_error(P, hyp, uv)
    inlier = err < tau
    inlier &= usable[:, :, None]
    count = inlier.sum(1)  # (C,Q,J)
    err[~inlier] = 0.0
    mean_err = err.sum(1) / np.maximum(count, 1)
    # most inliers first; mean_err / (2 tau) < 0.5 breaks ties without crossing counts
    key = np.where(np.isfinite(hyp[..., 0]), count - mean_err / (2.0 * tau), -1.0)
    best = np.argmax(key, axis=1)  # (C,J)
    best_inl = np.take_along_axis(inlier, best[:, None, None, :], axis=2)[:, :, 0]  # (C,M,J)
    n_inl = best_inl.sum(1)
    ok = n_inl >= min_views

    w2 = np.where(best_inl, weight[:, :, None] ** 2, 0.0)  # (C,M,J)
    X = solve_normal((E * w2).sum(2))  # (C,J,3) score-weighted DLT
    X = np.where(ok[..., None], X, np.nan)
    n_inl = np.where(np.isfinite(X).all(-1), n_inl, 0)
    return X, n_inl.astype(np.int64)


def mirror_permutation(num_joints: int) -> np.ndarray:
    """(J,) joint index of each joint's left/right counterpart (itself when central), for the
    keypoint convention with ``num_joints`` joints (core.skeleton); ValueError when none."""
    from maem_ros.core.skeleton import convention_for

    names = convention_for(num_joints).names
    idx = {n: i for i, n in enumerate(names)}
    swap = lambda n: n.replace("left", "\0").replace("right", "left").replace("\0", "right")  # noqa: E731
    return np.array([idx.get(swap(n), i) for i, n in enumerate(names)], dtype=np.int64)


#: views per cluster up to which every left/right labelling is tried (2^(M-1) combinations)
_MAX_LR_VIEWS = 12


def consistent_left_right(
    P: np.ndarray, uv: np.ndarray, score: np.ndarray, present: np.ndarray, mirror: np.ndarray
) -> np.ndarray:
    """(C,M) bool: which views of each cluster to relabel (swap left and right) for consistency.

    Pair residual r(a, b) = median over joints of the two-view DLT reprojection error (mean of
    the two views), for the pair as given and with a's labels mirrored; a labelling s (C,M) of
    flip bits costs sum over present pairs of r_same where s_a == s_b else r_flip.
    """
    C, M, J, _ = uv.shape
    if M > _MAX_LR_VIEWS or J == 0:
        return np.zeros((C, M), bool)
    uvm = uv[:, :, mirror]
    ia, ib = np.triu_indices(M, 1)
    pair = present[:, ia] & present[:, ib]  # (C,Q)
    r = []
    for first in (uv, uvm):
        use = np.isfinite(first[:, ia]).all(-1) & np.isfinite(uv[:, ib]).all(-1)  # (C,Q,J)
        Ea = normal_entries(P[:, ia, None], first[:, ia], use)
        Eb = normal_entries(P[:, ib, None], uv[:, ib], use)
        X = solve_normal(Ea + Eb)  # (C,Q,J,3)
        # each pair as a one-view, one-hypothesis "cluster" of reprojection_error
        Q = len(ia)
        flat = lambda a: a.reshape(C * Q, 1, *a.shape[2:])  # noqa: E731, B023 - used in this iteration
        ea = reprojection_error(flat(P[:, ia]), flat(X), flat(first[:, ia])).reshape(C, Q, J)
        eb = reprojection_error(flat(P[:, ib]), flat(X), flat(uv[:, ib])).reshape(C, Q, J)
        e = np.where(use & np.isfinite(ea) & np.isfinite(eb), 0.5 * (ea + eb), np.nan)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pairs: no evidence
            med = np.nanmedian(e, axis=-1)
        r.append(np.where(pair & np.isfinite(med), med, 0.0))
    r_same, r_flip = r  # (C,Q)
    # every labelling with view 0 unflipped; its complement is the same geometry
    bits = (np.arange(2 ** (M - 1))[:, None] >> np.arange(M - 1)[None]) & 1
    labels = np.concatenate([np.zeros((len(bits), 1), np.int64), bits], axis=1).astype(bool)
    differ = labels[:, ia] != labels[:, ib]  # (A,Q)
    cost = np.where(differ[None], r_flip[:, None], r_same[:, None]).sum(-1)  # (C,A)
    best = labels[np.argmin(cost, axis=1)] & present  # (C,M)
    # flip the less confident side: the complement when it flips less total score
    flipped_score = (score * best).sum(1)
    other = ~best & present
    return np.where(((score * other).sum(1) < flipped_score)[:, None], other, best)


def _num_joints(frames: Mapping[str, FrameDetections]) -> int:
    counts = {
        name: f.kpts2d.shape[1] for name, f in frames.items() if f.kpts2d.ndim == 3 and f.kpts2d.shape[0] > 0
    }
    if len(set(counts.values())) > 1:
        raise ValueError(f"frames: keypoint count differs between cameras: {counts}")
    if counts:
        return next(iter(counts.values()))
    return max((f.kpts2d.shape[1] for f in frames.values() if f.kpts2d.ndim == 3), default=0)
