"""Per-joint constant-velocity Kalman filter on a track's triangulated joints.

Two views at a narrow angle fix a joint well across the rays and poorly along them; the track's
motion fixes it well in every direction. Each confirmed track keeps, per joint, a position and a
velocity (world m, m/s) with their 6x6 covariance. A new triangulated joint X with covariance
C (core/triangulation/uncertainty.py) updates the state as a Kalman measurement, so the estimate
leans on the prediction exactly along the directions the views leave uncertain and follows the
views where they agree. Process noise: white acceleration of ``accel_std`` m/s^2 per axis.

A joint without a finite measurement or covariance keeps its prediction for the state but is
published as missing (NaN); a track unseen for more than ``max_gap_s`` restarts from its next
measurement. Everything is batched over a frame's tracks and joints.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from maem_ros.core.paramspec import Params, param


@dataclass
class JointFilterParams(Params):
    """The joint filter of tracked people (one field = one triangulation-node parameter)."""

    joint_filter: bool = param(
        True,
        "filter tracked people's joints over time with their "
        "triangulation covariance (constant velocity; off = each "
        "frame's triangulation as is, the paper)",
    )
    joint_accel_std: float = param(
        30.0, "m/s^2, joint acceleration std of the joint filter", minimum=0.0, exclusive_minimum=True
    )
    joint_filter_gap: float = param(
        0.5, "s, a track unseen this long restarts its joint filter", minimum=0.0, exclusive_minimum=True
    )

    def make(self) -> JointFilter | None:
        """The filter these parameters describe (None when off)."""
        return JointFilter(self.joint_accel_std, self.joint_filter_gap) if self.joint_filter else None


@dataclass
class _TrackState:
    stamp_ns: int
    x: np.ndarray  # (J,6) position, velocity
    P: np.ndarray  # (J,6,6)


class JointFilter:
    """Filters the joints of tracked people frame by frame (track ids >= 0; others pass)."""

    def __init__(self, accel_std: float = 30.0, max_gap_s: float = 0.5):
        if accel_std <= 0:
            raise ValueError(f"joint filter: accel_std {accel_std} must be > 0")
        self.accel_std = float(accel_std)
        self.max_gap_s = float(max_gap_s)
        self._tracks: dict[int, _TrackState] = {}

    def reset(self) -> None:
        self._tracks.clear()

    def update(
        self, stamp_ns: int, ids: np.ndarray, joints: np.ndarray, cov: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Filtered joints (P,J,3) m and their covariance (P,J,3,3) m^2 for one frame.

        ids (P,) track ids (< 0 = untracked: returned as given); joints (P,J,3) world m (NaN =
        missing); cov (P,J,3,3) their covariance (NaN = unknown: the joint passes unfiltered).
        """
        out_X, out_C = joints.copy(), cov.copy()
        tracked = [k for k, i in enumerate(np.asarray(ids)) if i >= 0]
        if not tracked:
            return out_X, out_C
        rows = np.asarray(tracked)
        x, P, fresh = self._predicted(stamp_ns, np.asarray(ids)[rows], joints[rows], cov[rows])
        z, R = joints[rows], cov[rows]
        usable = np.isfinite(z).all(-1) & np.isfinite(R).all((-1, -2))  # (T,J)
        x, P = _kalman_update(
            x,
            P,
            np.where(usable[..., None], z, 0.0),
            np.where(usable[..., None, None], R, np.eye(3)),
            usable & ~fresh,
        )
        # a fresh track starts at its measurement (zero velocity, wide velocity prior)
        x = np.where((fresh & usable)[..., None], _start_state(z), x)
        P = np.where((fresh & usable)[..., None, None], _start_cov(R), P)
        x[fresh & ~usable] = np.nan  # still no state: starts at its first measurement
        for n, k in enumerate(rows):
            self._tracks[int(ids[k])] = _TrackState(int(stamp_ns), x[n], P[n])
        out_X[rows] = np.where(usable[..., None], x[..., :3], np.nan)
        out_C[rows] = np.where(usable[..., None, None], P[..., :3, :3], np.nan)
        return out_X, out_C

    def _predicted(
        self, stamp_ns: int, ids: np.ndarray, z: np.ndarray, R: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each track's state predicted to stamp_ns (T,J,6), (T,J,6,6) and which are fresh."""
        T, J = z.shape[:2]
        x = np.zeros((T, J, 6))
        P = np.tile(np.eye(6), (T, J, 1, 1))
        fresh = np.ones((T, J), bool)
        for n, tid in enumerate(ids):  # one state per track: a loop over tracks, not joints
            st = self._tracks.get(int(tid))
            if st is None or st.x.shape[0] != J:
                continue
            dt = (stamp_ns - st.stamp_ns) * 1e-9
            if not 0 < dt <= self.max_gap_s:
                continue
            F, Q = _transition(dt, self.accel_std)
            known = np.isfinite(st.x).all(-1)  # joints never measured have no state
            x[n, known] = st.x[known] @ F.T
            P[n, known] = F @ st.P[known] @ F.T + Q
            fresh[n] = ~known
        return x, P, fresh


@functools.lru_cache(maxsize=64)
def _transition(dt: float, accel_std: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant-velocity transition F (6,6) and white-acceleration process noise Q (6,6).
    Cached (read-only arrays): every track of a steady stream has the same dt."""
    I3 = np.eye(3)
    F = np.block([[I3, dt * I3], [np.zeros((3, 3)), I3]])
    q = accel_std**2
    Q = q * np.block([[dt**4 / 4 * I3, dt**3 / 2 * I3], [dt**3 / 2 * I3, dt**2 * I3]])
    F.flags.writeable = Q.flags.writeable = False
    return F, Q


def _kalman_update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray, use: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position measurement update, batched over (T,J); rows with use False keep the prediction."""
    S = P[..., :3, :3] + R  # (T,J,3,3)
    K = np.linalg.solve(S, P[..., :3, :]).swapaxes(-1, -2)  # (T,J,6,3) = P H^T S^-1
    innovation = z - x[..., :3]
    x_new = x + np.einsum("tjab,tjb->tja", K, innovation)
    P_new = P - K @ P[..., :3, :]
    P_new = 0.5 * (P_new + P_new.swapaxes(-1, -2))
    return (np.where(use[..., None], x_new, x), np.where(use[..., None, None], P_new, P))


#: velocity std of a track's first frame, m/s (a person's limbs move at up to a few m/s)
_START_VELOCITY_STD = 3.0


def _start_state(z: np.ndarray) -> np.ndarray:
    return np.concatenate([z, np.zeros_like(z)], axis=-1)


def _start_cov(R: np.ndarray) -> np.ndarray:
    P = np.zeros(R.shape[:-2] + (6, 6))
    P[..., :3, :3] = R
    P[..., 3:, 3:] = np.eye(3) * _START_VELOCITY_STD**2
    return P


def filter_and_score(
    stamp_ns: int,
    ids: np.ndarray,
    joints: np.ndarray,
    cov: np.ndarray,
    detection_scores: np.ndarray,
    joint_filter: JointFilter | None,
    pose_score: str,
    score_ref_m: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What is published for one frame's tracked poses (the triangulation node and maem-eval):
    joints (P,J,3) world m filtered over time when ``joint_filter`` is given, their per-joint
    std (P,J) m and the scores (P,) (core/triangulation/uncertainty.pose_scores)."""
    from maem_ros.core.triangulation.uncertainty import joint_std, pose_scores

    if joint_filter is not None:
        joints, cov = joint_filter.update(stamp_ns, ids, joints, cov)
    std = joint_std(cov)
    return joints, std, pose_scores(np.asarray(detection_scores), std, pose_score, score_ref_m)
