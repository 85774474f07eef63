"""People over time: the clusters of consecutive frames linked into tracks, their 2D keypoints
per camera as dense arrays, linear triangulation, and moving a camera's 2D tracks in time.

Dense layout: U (C,T,F,J,2) rectified px of camera c, track T, frame F, joint J (NaN = not
seen, sides already unswapped); D (C,T,F) the detection row (-1 = none) for outlier groups.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..geometry.multiview import dlt
from .matching import Clusters
from .people_data import PeopleData

#: m (in the rig's units, about metres) a person may move between consecutive frames
LINK_GATE = 0.8


@dataclass
class Tracks:
    U: np.ndarray
    D: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int, int]:
        C, T, F, J, _ = self.U.shape
        return C, T, F, J


def projection_matrices(K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(C,3,4) K [R | t]."""
    return np.einsum("cij,cjk->cik", K, np.concatenate([R, t[:, :, None]], axis=2))


def triangulate(P: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Linear triangulation (geometry.multiview.dlt) in the tracks' layout: P (C,3,4),
    uv (C,...,2) px with NaN = unseen -> (...,3), NaN where fewer than two cameras (with
    finite projection matrices) see the point."""
    good = np.all(np.isfinite(P), axis=(1, 2))
    uv = np.where(good.reshape((-1,) + (1,) * (uv.ndim - 1)), uv, np.nan)
    P = np.where(good[:, None, None], P, 0.0)
    return dlt(P, np.moveaxis(uv, 0, -2))


def link_tracks(data: PeopleData, clusters: Clusters, P: np.ndarray) -> Tracks:
    """Tracks of clusters over consecutive frames (Hungarian on the distance of their
    triangulated centroids, under LINK_GATE), as dense arrays."""
    C, F, J = data.num_cameras, data.num_frames, data.joints.size
    n = clusters.num
    cu = np.full((C, n, J, 2), np.nan)
    cd = np.full((C, n), -1, np.int64)
    for c in range(C):
        m = clusters.camera == c
        kp = data.cameras[c].kpts2d[clusters.det[m]]
        kp = np.where(clusters.swapped[m, None, None], kp[:, data.flip], kp)
        cu[c, clusters.person[m]] = kp
        cd[c, clusters.person[m]] = clusters.det[m]
    with np.errstate(all="ignore"):  # median over joints: a hallucinated limb cannot move it
        centroid = np.nanmedian(triangulate(P, cu), axis=1) if n else np.zeros((0, 3))
    frame_of = np.zeros(n, np.int64)
    frame_of[clusters.person] = clusters.frame
    track_of = np.full(n, -1, np.int64)
    next_track = 0
    prev = np.zeros(0, np.int64)
    for f in range(F):
        cur = np.flatnonzero(frame_of == f)
        cur = cur[np.all(np.isfinite(centroid[cur]), axis=1)]
        if prev.size and cur.size:
            dist = np.linalg.norm(centroid[prev][:, None] - centroid[cur][None], axis=2)
            r, k = linear_sum_assignment(np.where(dist < LINK_GATE, dist, 1e6))
            ok = dist[r, k] < LINK_GATE
            track_of[cur[k[ok]]] = track_of[prev[r[ok]]]
        new = cur[track_of[cur] < 0]
        track_of[new] = next_track + np.arange(new.size)
        next_track += new.size
        prev = cur
    T = next_track
    U = np.full((C, T, F, J, 2), np.nan)
    D = np.full((C, T, F), -1, np.int64)
    ok = track_of >= 0
    U[:, track_of[ok], frame_of[ok]] = cu[:, ok]
    D[:, track_of[ok], frame_of[ok]] = cd[:, ok]
    return Tracks(U, D)


def shift_in_time(U: np.ndarray, delta: float) -> np.ndarray:
    """(T,F,J,2) one camera's tracks sampled at frame f - delta instead of f (linear
    interpolation between neighbouring frames of the same track; NaN where either is absent):
    the keypoints the camera would have seen at the reference times if it captured each of
    its frames ``delta`` frames late (a capture time offset of delta / fps s)."""
    F = U.shape[1]
    pos = np.arange(F) - delta
    f0 = np.floor(pos).astype(np.int64)
    a = (pos - f0)[None, :, None, None]
    inside = (f0 >= 0) & (f0 + 1 <= F - 1)
    f0c = np.clip(f0, 0, F - 1)
    f1c = np.clip(f0 + 1, 0, F - 1)
    out = (1 - a) * U[:, f0c] + a * U[:, f1c]
    exact = np.isclose(a[0, :, 0, 0], 0.0) & (f0 >= 0) & (f0 <= F - 1)
    out[:, exact] = U[:, f0c[exact]]
    out[:, ~(inside | exact)] = np.nan
    return out
