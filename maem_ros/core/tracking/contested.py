"""The order of a track stage camera's contested candidates (core/tracking/temporal.py, step 3).

A candidate pair (track t, detection n of camera c) is contested when the track has more than
one gated detection in c or the detection is gated for more than one track: two people close
together in one image. The 2D distance to the track's projected prediction cannot tell them
apart there (their predictions overlap), and a track whose prediction drifted onto the
neighbour then keeps the neighbour's detection frame after frame. The track's other views this
frame can: a detection of the same person agrees with them in 3D. Each contested pair's cost
gets ``pose_weight`` (px/m) times the mean association pair cost
(core.association.pipeline.pair_cost: PA-MPJPE of the lower camera's 3D pose aligned onto the
other's plus the epipolar term; a pair failing the pair gates counts as ``tau_cost``) between the
detection and the track's uncontested candidates (its only gated detection in a camera, gated
for no other track). Without uncontested views it falls back to ``pose_weight`` times the
PA-MPJPE of the detection's pose aligned onto the track's skeleton.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from maem_ros.core.association.params import AssociationParams
from maem_ros.core.geometry.procrustes import pa_mpjpe_finite
from maem_ros.core.tracking.pair_costs import FramePairCosts


class ContestView(Protocol):
    """What the contested cost reads of the track stage's frame view (temporal._FrameView)."""

    kp3: np.ndarray  # (C,N,J,3) body joints, camera m, NaN padded
    costs: FramePairCosts  # the frame set's pair decisions and capped costs


@dataclass(frozen=True)
class ContestSettings:
    """The settings the contested cost needs: the association's parameters and the stage's
    ``pose_weight`` (px per m)."""

    params: AssociationParams
    pose_weight: float


def contested_cost(
    cfg: ContestSettings, view: ContestView, okc: np.ndarray, joints: np.ndarray
) -> np.ndarray:
    """(C,T,N) px added to the assignment cost of the gated pairs okc (C,T,N) (cameras, tracks
    joints (T,J,3) world m, padded detections): 0 on uncontested pairs (module docstring)."""
    contested = okc & ((okc.sum(2, keepdims=True) > 1) | (okc.sum(1, keepdims=True) > 1))
    out = np.zeros(okc.shape)
    if not contested.any():
        return out
    if cfg.pose_weight <= 0:
        return out
    # one scale (m of pose disagreement) for both terms: a camera's contested pairs may mix them
    cons = consistency(cfg, view, okc, contested)
    fall = contested & ~np.isfinite(cons)
    out[contested & ~fall] = cons[contested & ~fall]
    if fall.any():
        out += pose_cost(fall, joints, view.kp3, cfg.params.execution.backend)
    return cfg.pose_weight * out


def consistency(
    cfg: ContestSettings, view: ContestView, okc: np.ndarray, contested: np.ndarray
) -> np.ndarray:
    """(C,T,N) m: mean pair cost of each contested pair's detection against the track's
    uncontested candidates in the other cameras; NaN where not contested or none."""
    anchor = okc & ~contested & (okc.sum(2, keepdims=True) == 1)  # (C,T,N)
    out = np.full(okc.shape, np.nan)
    ac, at, ad = np.nonzero(anchor)
    kc, kt, kd = np.nonzero(contested)
    k, a = np.nonzero((kt[:, None] == at[None]) & (kc[:, None] != ac[None]))  # pairs
    if k.size == 0:
        return out
    c1, d1, c2, d2 = kc[k], kd[k], ac[a], ad[a]
    lo = c1 < c2  # the gates and the cost take the lower camera first
    ca, cb = np.where(lo, c1, c2), np.where(lo, c2, c1)
    da, db = np.where(lo, d1, d2), np.where(lo, d2, d1)
    cost = view.costs.get(ca, cb, da, db)[1]
    sums = np.zeros(kc.size)
    np.add.at(sums, k, cost)
    n = np.bincount(k, minlength=kc.size)
    with np.errstate(invalid="ignore"):
        out[kc, kt, kd] = np.where(n > 0, sums / np.maximum(n, 1), np.nan)
    return out


def pose_cost(okc: np.ndarray, joints: np.ndarray, kpts3d: np.ndarray, backend: str = "auto") -> np.ndarray:
    """(C,T,N) PA-MPJPE (m) of each selected (okc) detection's 3D body pose (kpts3d (C,N,J,3))
    aligned onto the track's skeleton joints (T,J,3), one batched alignment over all cameras
    (procrustes backend); 0 where not selected or the track has unseen joints (no preference)."""
    out = np.zeros(okc.shape)
    c, t, n = np.nonzero(okc & np.isfinite(joints).all((1, 2))[None, :, None])
    if t.size:
        out[c, t, n] = np.nan_to_num(pa_mpjpe_finite(kpts3d[c, n], joints[t], backend))
    return out
