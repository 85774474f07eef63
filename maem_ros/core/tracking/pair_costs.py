"""The track stage's detection-pair decisions of one frame set (core/tracking/temporal.py).

Both of the stage's uses of a detection pair ask the same question of the association's pair
gates (core.association.gates: bbox-centre reprojection, epipolar on mesh vertices or
keypoints) and pair cost (core.association.pipeline.pair_cost: PA-MPJPE of the lower
camera's 3D pose aligned onto the other's plus the epipolar term):

- the verification of a track's candidates keeps a pair when it passes the gates and its cost
  is under ``tau_cost`` (``ok``);
- the order of contested candidates (core/tracking/contested.py) weighs the pair's cost,
  capped at ``tau_cost`` (a pair failing the gates costs the cap).

:class:`FramePairCosts` answers both from one computation per distinct pair and frame set. The
stage announces every pair it may ask about (:func:`same_track_pairs`: the detections gated for
one track in two cameras, a superset of the contested pairs and of the candidates it verifies)
before asking, so that one call of the gates decides them together: a call's fixed cost (the
epipolar gate's per-call preparation) is that of several hundred pairs.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from maem_ros.core.association.gates import FrameSet
from maem_ros.core.association.params import AssociationParams
from maem_ros.core.association.pipeline import pair_cost
from maem_ros.core.detections import PASSED, FrameDetections
from maem_ros.core.geometry.procrustes import pa_mpjpe_finite
from maem_ros.core.skeleton import joint_subset


class FramePairCosts:
    """Pair decisions of one frame set, each distinct pair computed once (module docstring).

    gates: the frame set's pair gates (with the stage's verification epipolar test);
    by_cam: camera index -> its detections; n: detections per camera after padding (pair keys);
    verify_epipolar: the epipolar variant the cost's epipolar term follows."""

    def __init__(
        self,
        gates: FrameSet,
        by_cam: Mapping[int, FrameDetections],
        params: AssociationParams,
        verify_epipolar: str,
        n_cameras: int,
        n: int,
    ):
        self.gates, self.by_cam, self.params = gates, by_cam, params
        self.verify_epipolar = verify_epipolar
        self.n_cameras, self.n = n_cameras, n
        self.cap = params.tau_cost if params.tau_cost > 0 else 1.0  # m
        self._keys = np.zeros(0, np.int64)  # sorted pair keys computed so far
        self._ok = np.zeros(0, bool)
        self._cost = np.zeros(0)

    def get(
        self, ca: np.ndarray, cb: np.ndarray, da: np.ndarray, db: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """For detection pairs (camera ca < cb, detections da, db; (S,) each): (ok (S,) bool:
        passes the pair gates and, with ``tau_cost`` > 0, costs less than it; cost (S,) m:
        the pair cost capped at ``tau_cost`` (1 m when the cap is off), the cap where the pair
        fails the gates or has too few joints)."""
        keys = ((ca * self.n_cameras + cb) * self.n + da) * self.n + db
        pos = np.minimum(np.searchsorted(self._keys, keys), max(self._keys.size - 1, 0))
        hit = self._keys[pos] == keys if self._keys.size else np.zeros(keys.size, bool)
        new_keys, first = np.unique(keys[~hit], return_index=True)
        if new_keys.size:
            s = np.flatnonzero(~hit)[first]
            ok, cost = self._compute(ca[s], cb[s], da[s], db[s])
            merged = np.concatenate([self._keys, new_keys])
            order = np.argsort(merged, kind="stable")
            self._keys = merged[order]
            self._ok = np.concatenate([self._ok, ok])[order]
            self._cost = np.concatenate([self._cost, cost])[order]
            pos = np.searchsorted(self._keys, keys)
        return self._ok[pos], self._cost[pos]

    def _compute(
        self, ca: np.ndarray, cb: np.ndarray, da: np.ndarray, db: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(ok, capped cost) of new pairs (:meth:`get`): one call of the gates, one batched
        alignment of the passing pairs' 3D poses."""
        p = self.params
        decided = self.gates.decide(ca, da, cb, db)
        ok = decided.stage == PASSED
        cost = np.full(ca.size, self.cap)
        s = np.flatnonzero(ok)
        if s.size:
            J = next(fd.num_joints for fd in self.by_cam.values() if fd.n)
            joints = joint_subset(p.cost_joints, J)
            X = np.empty((s.size, joints.size, 3))
            Y = np.empty_like(X)
            for c, fd in self.by_cam.items():  # one gather per camera
                X[ca[s] == c] = fd.kpts3d[da[s][ca[s] == c]][:, joints]
                Y[cb[s] == c] = fd.kpts3d[db[s][cb[s] == c]][:, joints]
            pose = pa_mpjpe_finite(X, Y, p.execution.backend)
            raw = pair_cost(pose, decided.epi[s], p, self.verify_epipolar)  # NaN: too few joints
            if p.tau_cost > 0:
                ok[s] = raw < p.tau_cost
            cost[s] = np.minimum(np.nan_to_num(raw, nan=self.cap), self.cap)
        return ok, cost


def same_track_pairs(okc: np.ndarray) -> tuple[np.ndarray, ...]:
    """(ca, cb, da, db) with ca < cb: every pair of detections gated for the same track in two
    cameras, from okc (C,T,N) bool (cameras, tracks, padded detections)."""
    c, t, d = np.nonzero(okc)
    i, j = np.nonzero((t[:, None] == t[None]) & (c[:, None] < c[None]))
    return c[i], c[j], d[i], d[j]
