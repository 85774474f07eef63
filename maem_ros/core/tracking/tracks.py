"""Persistent person ids over time: Hungarian assignment on 3D distance, constant velocity.

Each track keeps its last joints (J,3 world metres, NaN where never seen) and one
velocity of its joint centroid (m/s). Per update, tracks are predicted to the new stamp
(last joints + velocity * dt) and assigned to the new poses with scipy
linear_sum_assignment on the mean distance over joints finite in both (NaN-aware);
pairs at or beyond ``gate_m`` never match. A track gets an id once it has been
updated ``min_hits`` times (until then update() reports -1 for it) and dies when it
has not been updated for more than ``timeout_s``. Ids increase monotonically and are
never reused in the lifetime of the Tracker, not even across reset().

A stamp older than the previous update's stamp (bag loop, restart) resets the tracks
first; the poses of that update then start new tentative tracks. Equal stamps are a
normal update with dt = 0.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

_NO_MATCH = 1e9
#: weight of the newest velocity measurement (exponential smoothing of jittery centroids)
_VELOCITY_ALPHA = 0.5


def _centroid(joints: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(K,3) mean of each pose's joints (K,J,3) where mask (K,J); 0 where none."""
    return np.where(mask[..., None], joints, 0.0).sum(1) / np.maximum(mask.sum(1), 1)[:, None]


class Tracker:
    """Assign persistent ids to poses (P,J,3) arriving with increasing stamps.

    The live tracks are rows of a few arrays (joints (T,J,3), velocity (T,3), stamp, hits,
    id), so a frame's update is array operations over all its matched people.
    """

    def __init__(self, gate_m: float = 0.5, min_hits: int = 3, timeout_s: float = 1.0):
        if not np.isfinite(gate_m) or gate_m <= 0:
            raise ValueError(f"gate_m: must be a positive distance in metres, got {gate_m}")
        if int(min_hits) != min_hits or min_hits < 1:
            raise ValueError(f"min_hits: must be an integer >= 1, got {min_hits}")
        if not np.isfinite(timeout_s) or timeout_s <= 0:
            raise ValueError(f"timeout_s: must be positive seconds, got {timeout_s}")
        self.gate_m = float(gate_m)
        self.min_hits = int(min_hits)
        self.timeout_ns = int(round(timeout_s * 1e9))
        self._next_id = 0
        self.resets = 0
        self.reset()

    @property
    def num_tracks(self) -> int:
        """Live tracks, tentative ones included."""
        return int(self._stamp.size)

    def reset(self) -> None:
        """Forget all tracks (the id counter keeps counting: ids are never reused)."""
        self._joints = np.zeros((0, 0, 3))  # (T,J,3) world m, NaN = never seen
        self._velocity = np.zeros((0, 3))  # (T,3) m/s of the joint centroid
        self._stamp = np.zeros(0, np.int64)  # (T,) ns of the last update
        self._hits = np.zeros(0, np.int64)
        self._id = np.zeros(0, np.int64)  # -1 until confirmed
        self._last_stamp: int | None = None

    def update(self, stamp_ns: int, joints: np.ndarray) -> np.ndarray:
        """Feed the poses of one frame; return (P,) int64 ids, -1 = tentative or untrackable.

        joints (P,J,3) world metres, NaN = missing joint. A pose without any finite joint
        cannot be tracked and gets -1 without starting a track.
        """
        joints = np.asarray(joints, dtype=np.float64)
        if joints.ndim != 3 or joints.shape[2] != 3:
            raise ValueError(f"joints: expected shape (P,J,3), got {joints.shape}")
        if np.isinf(joints).any():
            raise ValueError("joints: contains inf (missing joints must be NaN)")
        stamp_ns = int(stamp_ns)
        if self._last_stamp is not None and stamp_ns < self._last_stamp:
            self.reset()
            self.resets += 1
        self._last_stamp = stamp_ns
        self._keep(stamp_ns - self._stamp <= self.timeout_ns)
        if self.num_tracks and self._joints.shape[1] != joints.shape[1]:
            raise ValueError(
                f"joints: {joints.shape[1]} joints per pose, tracks have {self._joints.shape[1]}"
            )

        ids = np.full(joints.shape[0], -1, np.int64)
        rows, cols = self._assign(stamp_ns, joints)
        self._update_tracks(rows, stamp_ns, joints[cols])
        ids[cols] = self._id[rows]
        matched = np.zeros(joints.shape[0], bool)
        matched[cols] = True
        new = np.flatnonzero(~matched & np.isfinite(joints).all(-1).any(-1))
        ids[new] = self._add_tracks(stamp_ns, joints[new])
        return ids

    def _keep(self, keep: np.ndarray) -> None:
        self._joints, self._velocity = self._joints[keep], self._velocity[keep]
        self._stamp, self._hits, self._id = self._stamp[keep], self._hits[keep], self._id[keep]

    def _predicted(self, stamp_ns: int) -> np.ndarray:
        """(T,J,3) track joints moved to stamp_ns at constant centroid velocity."""
        dt = (stamp_ns - self._stamp) * 1e-9
        return self._joints + (self._velocity * dt[:, None])[:, None, :]

    def _assign(self, stamp_ns: int, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self.num_tracks or joints.shape[0] == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        pred = self._predicted(stamp_ns)
        both = np.isfinite(pred).all(-1)[:, None] & np.isfinite(joints).all(-1)[None]  # (T,P,J)
        with np.errstate(invalid="ignore"):
            d = np.linalg.norm(pred[:, None] - joints[None], axis=-1)
        n = both.sum(-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cost = np.where(both, d, 0.0).sum(-1) / n
        ok = (n > 0) & (cost < self.gate_m)
        rows, cols = linear_sum_assignment(np.where(ok, cost, _NO_MATCH))
        keep = ok[rows, cols]
        return rows[keep], cols[keep]

    def _update_tracks(self, rows: np.ndarray, stamp_ns: int, joints: np.ndarray) -> None:
        """Tracks ``rows`` (K,) (ascending) take the matched poses joints (K,J,3)."""
        if not rows.size:
            return
        last = self._joints[rows]
        seen = np.isfinite(joints).all(-1)  # (K,J)
        common = seen & np.isfinite(last).all(-1)
        dt = (stamp_ns - self._stamp[rows]) * 1e-9
        moved = (dt > 0) & common.any(-1)
        with np.errstate(invalid="ignore", divide="ignore"):  # rows not moved: discarded
            v = (_centroid(joints, common) - _centroid(last, common)) / dt[:, None]
        smoothed = np.where(
            (self._hits[rows] == 1)[:, None],
            v,
            _VELOCITY_ALPHA * v + (1 - _VELOCITY_ALPHA) * self._velocity[rows],
        )
        velocity = np.where(moved[:, None], smoothed, self._velocity[rows])
        # joints not seen now keep their last position, carried along by the velocity
        carried = last + velocity[:, None, :] * np.maximum(dt, 0.0)[:, None, None]
        self._joints[rows] = np.where(seen[..., None], joints, carried)
        self._velocity[rows] = velocity
        self._stamp[rows] = stamp_ns
        self._hits[rows] += 1
        self._confirm(rows)

    def _add_tracks(self, stamp_ns: int, joints: np.ndarray) -> np.ndarray:
        """New tentative tracks for poses joints (K,J,3), in order; returns their ids."""
        K = joints.shape[0]
        rows = np.arange(self.num_tracks, self.num_tracks + K)
        if not self.num_tracks:
            self._joints = np.zeros((0,) + joints.shape[1:])
        self._joints = np.concatenate([self._joints, joints])
        self._velocity = np.concatenate([self._velocity, np.zeros((K, 3))])
        self._stamp = np.concatenate([self._stamp, np.full(K, stamp_ns, np.int64)])
        self._hits = np.concatenate([self._hits, np.ones(K, np.int64)])
        self._id = np.concatenate([self._id, np.full(K, -1, np.int64)])
        self._confirm(rows)
        return self._id[rows]

    def _confirm(self, rows: np.ndarray) -> None:
        """Give the tentative tracks among ``rows`` with min_hits updates the next ids, in
        the order of ``rows``."""
        now = rows[(self._id[rows] < 0) & (self._hits[rows] >= self.min_hits)]
        self._id[now] = self._next_id + np.arange(now.size)
        self._next_id += int(now.size)
