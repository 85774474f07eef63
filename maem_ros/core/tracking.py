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

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

_NO_MATCH = 1e9
#: weight of the newest velocity measurement (exponential smoothing of jittery centroids)
_VELOCITY_ALPHA = 0.5


@dataclass
class _Track:
    joints: np.ndarray  # (J,3) world m, NaN = never seen
    velocity: np.ndarray  # (3,) m/s of the joint centroid
    stamp_ns: int
    hits: int
    id: int = -1


def _centroid(joints: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask[:, None], joints, 0.0).sum(0) / max(int(mask.sum()), 1)


class Tracker:
    """Assign persistent ids to poses (P,J,3) arriving with increasing stamps."""

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
        self._tracks: list[_Track] = []
        self._next_id = 0
        self._last_stamp: int | None = None
        self.resets = 0

    @property
    def num_tracks(self) -> int:
        """Live tracks, tentative ones included."""
        return len(self._tracks)

    def reset(self) -> None:
        """Forget all tracks (the id counter keeps counting: ids are never reused)."""
        self._tracks = []
        self._last_stamp = None

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
        self._tracks = [t for t in self._tracks if stamp_ns - t.stamp_ns <= self.timeout_ns]
        if self._tracks and self._tracks[0].joints.shape[0] != joints.shape[1]:
            raise ValueError(f"joints: {joints.shape[1]} joints per pose, tracks have "
                             f"{self._tracks[0].joints.shape[0]}")

        ids = np.full(joints.shape[0], -1, np.int64)
        rows, cols = self._assign(stamp_ns, joints)
        for r, c in zip(rows, cols):  # one iteration per matched person
            self._update_track(self._tracks[r], stamp_ns, joints[c])
            ids[c] = self._tracks[r].id
        matched = np.zeros(joints.shape[0], bool)
        matched[cols] = True
        trackable = np.isfinite(joints).all(-1).any(-1)
        for c in np.nonzero(~matched & trackable)[0]:
            track = _Track(joints[c].copy(), np.zeros(3), stamp_ns, 1)
            self._confirm(track)
            self._tracks.append(track)
            ids[c] = track.id
        return ids

    def _predicted(self, stamp_ns: int) -> np.ndarray:
        """(T,J,3) track joints moved to stamp_ns at constant centroid velocity."""
        if not self._tracks:
            return np.zeros((0, 0, 3))
        last = np.stack([t.joints for t in self._tracks])
        vel = np.stack([t.velocity for t in self._tracks])
        dt = np.array([(stamp_ns - t.stamp_ns) * 1e-9 for t in self._tracks])
        return last + (vel * dt[:, None])[:, None, :]

    def _assign(self, stamp_ns: int, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if not self._tracks or joints.shape[0] == 0:
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

    def _update_track(self, track: _Track, stamp_ns: int, joints: np.ndarray) -> None:
        seen = np.isfinite(joints).all(-1)
        common = seen & np.isfinite(track.joints).all(-1)
        dt = (stamp_ns - track.stamp_ns) * 1e-9
        if dt > 0 and common.any():
            v = (_centroid(joints, common) - _centroid(track.joints, common)) / dt
            track.velocity = v if track.hits == 1 else (
                _VELOCITY_ALPHA * v + (1 - _VELOCITY_ALPHA) * track.velocity)
        # joints not seen now keep their last position, carried along by the velocity
        carried = track.joints + track.velocity * max(dt, 0.0)
        track.joints = np.where(seen[:, None], joints, carried)
        track.stamp_ns = stamp_ns
        track.hits += 1
        self._confirm(track)

    def _confirm(self, track: _Track) -> None:
        if track.id < 0 and track.hits >= self.min_hits:
            track.id = self._next_id
            self._next_id += 1
