"""The world frame of a self-calibrated rig: floor, up, origin, axes and scale.

* Up (z): the normal of the plane the lowest foot joint of every person and frame lies on (a
  robust plane fit), signed towards the heads.
* Origin and x: the median and main direction (PCA) of the people's floor positions, x signed
  so that the first camera lies at x <= 0; y = z x x.
* Scale: metric skeletons (median ratio of the detections' camera-frame bone lengths to the
  triangulated ones), or ``person_height`` (m, the people's median stature, from pose-invariant
  bone chains with Drillis & Contini's segment fractions: ankle 0.039, knee 0.285, hip 0.530,
  shoulder 0.818 of stature; nose ~0.91), or court points (:mod:`.court`), which fix everything.

The result is a similarity X_world = s Q X + d applied to the rig and the points.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

#: segment fractions of stature (Drillis & Contini 1966): floor to ankle/knee/hip/shoulder/nose
_FRACTION = {"ankle": 0.039, "knee": 0.285, "hip": 0.530, "shoulder": 0.818, "nose": 0.91}
_BONES = (
    ("left_shoulder", "left_elbow"),
    ("right_shoulder", "right_elbow"),
    ("left_hip", "left_knee"),
    ("right_hip", "right_knee"),
    ("left_knee", "left_ankle"),
    ("right_knee", "right_ankle"),
    ("left_shoulder", "left_hip"),
    ("right_shoulder", "right_hip"),
    ("left_hip", "right_hip"),
    ("left_shoulder", "right_shoulder"),
)


@dataclass
class Similarity:
    """X_world = s Q X + d (Q rotation, s > 0 scale)."""

    s: float
    Q: np.ndarray
    d: np.ndarray

    def apply(self, X: np.ndarray) -> np.ndarray:
        return self.s * X @ self.Q.T + self.d

    def camera(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World->camera (R, t) of a camera after the change of frame (camera frame in m)."""
        Rn = R @ self.Q.T
        return Rn, self.s * t - Rn @ self.d

    def then(self, other: Similarity) -> Similarity:
        """This similarity followed by ``other``."""
        return Similarity(other.s * self.s, other.Q @ self.Q, other.s * other.Q @ self.d + other.d)


def _bone_lengths(X: np.ndarray, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    pos = {n: k for k, n in enumerate(names)}
    out = {}
    for a, b in _BONES:
        if a in pos and b in pos:
            out[f"{a}-{b}"] = np.linalg.norm(X[..., pos[a], :] - X[..., pos[b], :], axis=-1).ravel()
    return out


def skeleton_scale(
    X: np.ndarray, rows: np.ndarray, kpts3d: list[np.ndarray], names: tuple[str, ...]
) -> float:
    """Metres per rig unit: the median over every (camera, track, frame, bone) of the
    detection's metric bone length (its camera-frame 3D keypoints) over the triangulated one.
    X (T,F,J,3) rig units; rows (C,T,F) the detection row of each camera (-1 = none); NaN
    without a common bone."""
    ratios: list[np.ndarray] = []
    tri = _bone_lengths(X, names)  # per bone: (T*F,)
    for c, kp in enumerate(kpts3d):
        have = rows[c].ravel() >= 0
        if not have.any():
            continue
        metric = _bone_lengths(kp[rows[c].ravel()[have]], names)
        for bone, length in tri.items():
            with np.errstate(invalid="ignore", divide="ignore"):
                r = metric[bone] / length[have]
            ratios.append(r[np.isfinite(r) & (r > 0)])
    every = np.concatenate(ratios) if ratios else np.zeros(0)
    return float(np.median(every)) if every.size else np.nan


def stature(X: np.ndarray, names: tuple[str, ...]) -> float:
    """Median stature (rig units) of the triangulated people X (...,J,3) from the median
    lengths of shin, thigh, torso (hip to shoulder) and shoulder to nose, each divided by its
    fraction of stature; NaN if the joints are missing."""
    pos = {n: k for k, n in enumerate(names)}
    chain = (("ankle", "knee"), ("knee", "hip"), ("hip", "shoulder"), ("shoulder", "nose"))
    est = []
    for lo, hi in chain:
        la = [f"{s}_{lo}" if lo != "nose" else "nose" for s in ("left", "right")]
        lb = [f"{s}_{hi}" if hi != "nose" else "nose" for s in ("left", "right")]
        if not all(n in pos for n in la + lb):
            return np.nan
        length = np.concatenate(
            [np.linalg.norm(X[..., pos[a], :] - X[..., pos[b], :], axis=-1).ravel() for a, b in zip(la, lb)]
        )
        est.append(np.nanmedian(length))
    return float(sum(est) / (_FRACTION["nose"] - _FRACTION["ankle"]))


def floor_frame(X: np.ndarray, feet: np.ndarray, head: np.ndarray, first_centre: np.ndarray) -> Similarity:
    """Rotation and origin (scale 1) putting the people's floor at z = 0, z up, origin and x at
    the centre and main direction of their floor positions. X (T,F,J,3) rig units."""
    up0 = _body_up(X, feet, head)
    foot = X[:, :, feet]
    h = np.einsum("tfjk,k->tfj", foot, up0)
    with np.errstate(all="ignore"):
        low = np.nanargmin(np.where(np.isfinite(h), h, np.inf), axis=2)
    lowest = np.take_along_axis(foot, low[:, :, None, None], axis=2)[:, :, 0].reshape(-1, 3)
    pts = lowest[np.all(np.isfinite(lowest), axis=1)]
    if len(pts) < 3:
        raise ValueError("world frame: too few foot positions to find the floor")
    n = up0
    level = np.median(pts @ n)
    spread = np.median(np.abs(pts @ n - level)) + 1e-9
    for _ in range(5):
        hp = pts @ n
        level = np.percentile(hp, 30)
        near = np.abs(hp - level) < 3 * spread
        cen = pts[near].mean(0)
        n_new = np.linalg.svd(pts[near] - cen, full_matrices=False)[2][2]
        n = n_new * np.sign(n_new @ up0)
        spread = max(np.median(np.abs((pts[near] - cen) @ n)), 1e-3 * spread)
    z = n
    floor = pts - np.outer(pts @ z - cen @ z, z)
    origin = np.median(floor, axis=0)
    in_plane = floor - origin
    in_plane -= np.outer(in_plane @ z, z)
    x = np.linalg.svd(in_plane, full_matrices=False)[2][0]
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    if (first_centre - origin) @ x > 0:
        x = -x
    y = np.cross(z, x)
    Q = np.stack([x, y, z])
    return Similarity(1.0, Q, -Q @ origin)


def _body_up(X: np.ndarray, feet: np.ndarray, head: np.ndarray) -> np.ndarray:
    """Mean direction from the feet to the head over all people and frames (unit)."""
    top = X[:, :, head].reshape(-1, len(head), 3) if len(head) else X.reshape(-1, X.shape[2], 3)
    with warnings.catch_warnings():  # people seen without head or feet give NaN: dropped below
        warnings.simplefilter("ignore", RuntimeWarning)  # nanmean of all-NaN
        v = np.nanmean(top, axis=1) - np.nanmean(X[:, :, feet].reshape(-1, len(feet), 3), axis=1)
    v = v[np.all(np.isfinite(v), axis=1) & (np.linalg.norm(v, axis=1) > 0)]
    if len(v) == 0:
        raise ValueError("world frame: no person seen with both feet and head")
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    m = np.median(v, axis=0)
    return m / np.linalg.norm(m)
