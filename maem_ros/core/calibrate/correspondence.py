"""Relative pose of a camera pair from people, without any geometry to start from.

Every (detection in camera a, detection in camera b) of one frame is a hypothesis that both
see the same person: aligning b's camera-frame 3D skeleton onto a's (rotation of a Umeyama fit,
core.geometry.procrustes) gives a rotation R_ab (X_a = R_ab X_b + t_ab). Each hypothesis is also tried
with b's left and right swapped (a detector that confuses the sides). The pairs of one person
agree on R_ab, other pairs scatter: the rotation most hypotheses agree with wins (consensus).
Among the hypotheses that agree, the translation direction is the one most pairs' 2D keypoints
satisfy the epipolar constraint with (x_a . (t x R x_b) = 0, RANSAC over single pairs, each
giving t from its joints), its length the median of the pairs' 3D centroid offsets along it
(metric, from the skeletons). Several people, referees, false positives and swapped sides only
add hypotheses that disagree.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry.procrustes import procrustes_align
from ..tracking.track_geometry import nanmedian
from .people_data import PeopleData, normalised

#: consensus thresholds: rotation (deg) of the first vote and of the refined one
ROTATION_VOTE_DEG = 12.0
ROTATION_INLIER_DEG = 8.0
#: a pair agrees with a translation when the median epipolar angle of its joints is under this
EPIPOLAR_INLIER_PX = 12.0
#: fewer agreeing detection pairs than this: the camera pair has too little shared evidence
MIN_SUPPORT = 8
_MAX_CANDIDATES = 400


@dataclass
class PairEstimate:
    """Relative pose of cameras a < b: X_a = R X_b + t (t in m from the skeletons' scale);
    ``support``: detection pairs (over all frames) agreeing with it; ``matches`` (support, 4)
    their (frame, detection in a, detection in b, swapped)."""

    a: int
    b: int
    R: np.ndarray
    t: np.ndarray
    support: int
    matches: np.ndarray


def _hypotheses(data: PeopleData, a: int, b: int, frames: np.ndarray):
    """All (frame, i, j, swap) detection pairs of the frames with their rotations (H,3,3),
    scales (H,) and metric centroid offsets t3d (H,3) (a's centroid - R b's centroid)."""
    ca, cb = data.cameras[a], data.cameras[b]
    rows = []
    for f in frames:
        ia = np.arange(ca.frame(f).start, ca.frame(f).stop)
        ib = np.arange(cb.frame(f).start, cb.frame(f).stop)
        if ia.size and ib.size:
            Ia, Jb = np.meshgrid(ia, ib, indexing="ij")
            rows.append(np.column_stack([np.full(Ia.size, f), Ia.ravel(), Jb.ravel()]))
    if not rows:
        return np.zeros((0, 4), np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3))
    pairs = np.concatenate(rows)
    pairs = np.concatenate(
        [
            np.column_stack([pairs, np.zeros(len(pairs), np.int64)]),
            np.column_stack([pairs, np.ones(len(pairs), np.int64)]),
        ]
    )
    Y = ca.kpts3d[pairs[:, 1]]
    X = cb.kpts3d[pairs[:, 2]]
    X = np.where(pairs[:, 3, None, None] == 1, X[:, data.flip], X)
    _, s, R, _ = procrustes_align(X, Y)
    t3d = np.nanmean(Y, axis=1) - np.einsum("nij,nj->ni", R, np.nanmean(X, axis=1))
    ok = np.isfinite(s)
    return pairs[ok], R[ok], t3d[ok]


def _rotation_consensus(R: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(consensus rotation, inlier mask) of hypotheses R (H,3,3)."""
    q = Rotation.from_matrix(R).as_quat()
    cand = q if len(q) <= _MAX_CANDIDATES else q[rng.choice(len(q), _MAX_CANDIDATES, replace=False)]
    vote = np.abs(cand @ q.T) > np.cos(np.radians(ROTATION_VOTE_DEG) / 2)
    best = cand[np.argmax(vote.sum(1))]
    for deg in (ROTATION_VOTE_DEG, ROTATION_INLIER_DEG, ROTATION_INLIER_DEG):
        dots = q @ best
        near = np.abs(dots) > np.cos(np.radians(deg) / 2)
        mean = (q[near] * np.sign(dots[near])[:, None]).sum(0)
        best = mean / np.linalg.norm(mean)
    near = np.abs(q @ best) > np.cos(np.radians(ROTATION_INLIER_DEG) / 2)
    return Rotation.from_quat(best).as_matrix(), near


def _epipolar_rows(data: PeopleData, a: int, b: int, pairs: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(H,J,3) rows R x_b x x_a of every hypothesis' joints (NaN where a joint is unseen); a
    translation t satisfies rows . t = 0 (the epipolar constraint)."""
    xa = normalised(data.rig, a, data.cameras[a].kpts2d[pairs[:, 1]])
    kb = data.cameras[b].kpts2d[pairs[:, 2]]
    kb = np.where(pairs[:, 3, None, None] == 1, kb[:, data.flip], kb)
    xb = normalised(data.rig, b, kb)
    ha = np.concatenate([xa, np.ones(xa.shape[:2] + (1,))], axis=2)
    hb = np.concatenate([xb, np.ones(xb.shape[:2] + (1,))], axis=2)
    rows = np.cross(hb @ R.T, ha)
    norm = np.linalg.norm(rows, axis=2, keepdims=True)
    return rows / np.where(norm > 0, norm, np.nan)


def _translation_consensus(rows: np.ndarray, t3d: np.ndarray, tol: float):
    """(unit t, inlier mask) from per-hypothesis epipolar rows (H,J,3): each hypothesis' own
    null vector is a candidate; the one most hypotheses agree with (median |row . t| < tol)
    wins, then t is refit on the inliers' rows. The sign follows the 3D centroid offsets."""
    filled = np.nan_to_num(rows)
    _, _, Vt = np.linalg.svd(filled)
    cand = Vt[:, 2]
    cand *= np.sign(np.einsum("ni,ni->n", cand, t3d))[:, None]
    if len(cand) > _MAX_CANDIDATES:
        cand = cand[np.linspace(0, len(cand) - 1, _MAX_CANDIDATES).astype(int)]
    err = nanmedian(np.abs(np.einsum("hji,ci->chj", rows, cand)))  # (cand,H)
    best = cand[np.argmax((err < tol).sum(1))]
    for _ in range(3):
        inl = nanmedian(np.abs(rows @ best)) < tol
        stack = filled[inl].reshape(-1, 3)
        if len(stack) < 3:
            break
        v = np.linalg.svd(stack, full_matrices=False)[2][2]
        best = v * np.sign(v @ np.median(t3d[inl], axis=0))
    inl = nanmedian(np.abs(rows @ best)) < tol
    return best, inl


def estimate_pair(
    data: PeopleData, a: int, b: int, frames: np.ndarray, rng: np.random.Generator
) -> PairEstimate | None:
    """The relative pose of cameras a, b from the detections of ``frames`` (None when no
    detection pair exists)."""
    pairs, R, t3d = _hypotheses(data, a, b, frames)
    if len(pairs) < 3:
        return None
    R_ab, rot_in = _rotation_consensus(R, rng)
    pairs, t3d = pairs[rot_in], t3d[rot_in]
    if len(pairs) < 2:
        return PairEstimate(a, b, R_ab, np.full(3, np.nan), 0, np.zeros((0, 4), np.int64))
    rows = _epipolar_rows(data, a, b, pairs, R_ab)
    f = 0.5 * (data.rig[a].K_rect[0, 0] + data.rig[b].K_rect[0, 0])
    t_dir, t_in = _translation_consensus(rows, t3d, EPIPOLAR_INLIER_PX / f)
    matches = _one_to_one(pairs[t_in], nanmedian(np.abs(rows[t_in] @ t_dir)))
    keep = np.isin(np.arange(len(pairs)), np.flatnonzero(t_in)[matches])
    length = float(np.median(t3d[keep] @ t_dir)) if keep.any() else np.nan
    return PairEstimate(a, b, R_ab, t_dir * length, int(keep.sum()), pairs[keep])


def _one_to_one(pairs: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Indices of ``pairs`` keeping, per frame, each detection of a and of b at most once
    (greedy by cost: a detection agrees with one person of the other view)."""
    order = np.argsort(cost, kind="stable")
    used_a, used_b, keep = set(), set(), []
    for k in order:
        f, i, j = int(pairs[k, 0]), int(pairs[k, 1]), int(pairs[k, 2])
        if (f, i) in used_a or (f, j) in used_b:
            continue
        used_a.add((f, i))
        used_b.add((f, j))
        keep.append(k)
    return np.array(keep, np.int64)


def hypothesis_frames(data: PeopleData, max_frames: int) -> np.ndarray:
    """Up to ``max_frames`` frames spread evenly over the sequence (the pair search's cost
    grows with frames x people^2)."""
    F = data.num_frames
    return np.unique(np.linspace(0, F - 1, min(F, max_frames)).round().astype(np.int64))
