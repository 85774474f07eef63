"""The track stage's state (core.tracking.temporal): each person's root (mean of the finite
body joints) as a constant-velocity Kalman filter (m, m/s) and the body joints as offsets from
it, smoothed with weight ``joint_alpha`` on the newest pose; a track gets an id after
``confirm_hits`` supported frames."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


class FilterParams(Protocol):
    """The TemporalParams the filter reads."""

    accel_std: float  # m/s^2, process noise of the root
    meas_std: float  # m, root measurement std
    joint_alpha: float  # weight of the newest pose in the per-joint smoothing
    confirm_hits: int  # supported frames before a track gets an id


@dataclass
class Track:
    """One person followed through time. x (6,) root position (m) and velocity (m/s), Pc (6,6)
    its covariance; offsets (J,3) body joints minus root (m, NaN = never seen)."""

    key: int
    x: np.ndarray
    Pc: np.ndarray
    offsets: np.ndarray
    hits: int = 1
    misses: int = 0
    id: int = -1

    @property
    def joints(self) -> np.ndarray:
        """(J,3) predicted / current body joints, world m."""
        return self.x[:3] + self.offsets


def root_of(joints: np.ndarray) -> np.ndarray:
    """(...,3) mean of the finite joints of (...,J,3); NaN if none."""
    ok = np.isfinite(joints).all(-1)
    n = ok.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok[..., None], joints, 0.0).sum(-2) / n[..., None]


class Tracker3D:
    """Kalman root + smoothed offsets for a list of tracks (module docstring)."""

    def __init__(self, params: FilterParams):
        self.p = params
        self.tracks: list[Track] = []
        self._next_key = 0
        self._next_id = 0

    def reset(self) -> None:
        """End every track (the id counter keeps counting)."""
        self.tracks = []

    def predict(self, dt: float) -> None:
        """Move every track forward by dt seconds (constant velocity, white acceleration)."""
        if not self.tracks or dt <= 0:
            return
        F = np.eye(6)
        F[:3, 3:] = dt * np.eye(3)
        q = self.p.accel_std**2
        Q1 = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        Q = np.kron(Q1, np.eye(3))
        # every track in one batched product: per-track numpy calls cost more than the maths
        x = np.stack([t.x for t in self.tracks]) @ F.T
        Pc = F @ np.stack([t.Pc for t in self.tracks]) @ F.T + Q
        for t, xi, Pi in zip(self.tracks, x, Pc):
            t.x, t.Pc = xi, Pi

    def start(self, joints: np.ndarray) -> Track:
        """A tentative track from a triangulated pose (J,3)."""
        root = root_of(joints)
        Pc = np.diag([self.p.meas_std**2] * 3 + [4.0] * 3)  # velocity unknown: ~2 m/s std
        t = Track(self._next_key, np.concatenate([root, np.zeros(3)]), Pc, joints - root)
        self._next_key += 1
        self.tracks.append(t)
        self._confirm(t)
        return t

    def update(self, t: Track, joints: np.ndarray, meas_std: float | None = None) -> None:
        """Kalman update of the root with a pose (J,3) (NaN = unseen), smooth the offsets."""
        self.update_many([t], joints[None], meas_std)

    def update_many(self, tracks: list[Track], joints: np.ndarray, meas_std: float | None = None) -> None:
        """:meth:`update` of each track with its pose (K,J,3), batched over the tracks (the
        per-track numpy calls cost more than the maths); ids go to newly confirmed tracks in
        the given order."""
        root = root_of(joints)  # (K,3)
        idx = np.flatnonzero(np.isfinite(root).all(-1))
        if idx.size:
            upd = [tracks[i] for i in idx]
            x, Pc = np.stack([t.x for t in upd]), np.stack([t.Pc for t in upd])
            r = (meas_std or self.p.meas_std) ** 2
            S = Pc[:, :3, :3] + r * np.eye(3)
            K = Pc[:, :, :3] @ np.linalg.inv(S)  # (k,6,3) Kalman gains
            x = x + (K @ (root[idx] - x[:, :3])[:, :, None])[:, :, 0]
            Pc = (np.eye(6) - K @ np.eye(3, 6)) @ Pc
            new = joints[idx] - root[idx, None]
            old = np.stack([t.offsets for t in upd])
            a = self.p.joint_alpha
            seen, known = np.isfinite(new).all(-1), np.isfinite(old).all(-1)
            blend = np.where((seen & known)[..., None], a * new + (1 - a) * old, old)
            offsets = np.where((seen & ~known)[..., None], new, blend)
            for t, xi, Pi, oi in zip(upd, x, Pc, offsets):
                t.x, t.Pc, t.offsets = xi, Pi, oi
        for t in tracks:
            t.hits += 1
            t.misses = 0
            self._confirm(t)

    def _confirm(self, t: Track) -> None:
        if t.id < 0 and t.hits >= self.p.confirm_hits:
            t.id = self._next_id
            self._next_id += 1
