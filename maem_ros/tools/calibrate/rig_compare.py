"""A calibrated rig against a reference rig of the same cameras (a Qualisys calibration, a
simulated scene's true rig): the measures of issue 35's targets, and the similarity that moves
the calibrated rig into the reference's world frame.

* relative rotation of every camera pair (deg): the angle of (R_a R_b^T)_est (R_a R_b^T)_ref^T,
  independent of either world frame;
* camera centres after the least-squares similarity (scale, rotation, translation) of the
  calibrated centres onto the reference's (m of the reference);
* scale: the calibrated rig's size over the reference's (1 = metric, when the reference is);
* up: the angle between the two rigs' world z, seen from the cameras (median over cameras);
* time offsets (s): calibrated minus reference, after removing their median (only relative
  offsets are observable).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from maem_ros.core.calibrate.world import Similarity
from maem_ros.core.geometry.camera import Rig
from maem_ros.core.geometry.procrustes import procrustes_align


@dataclass
class RigComparison:
    """Errors of a calibrated rig against a reference (see the module docstring); per pair
    and per camera in ``names`` order; lengths in the reference's units (m)."""

    names: list[str]
    pairs: list[tuple[str, str]]
    rotation_deg: np.ndarray
    centre_m: np.ndarray
    scale: float
    up_deg: float
    offset_s: np.ndarray
    radius_m: float

    def summary(self) -> dict[str, float]:
        return {
            "rot_median_deg": float(np.median(self.rotation_deg)),
            "rot_max_deg": float(np.max(self.rotation_deg)),
            "centre_median_m": float(np.median(self.centre_m)),
            "centre_max_m": float(np.max(self.centre_m)),
            "centre_max_pct_radius": float(100 * np.max(self.centre_m) / self.radius_m),
            "scale_error_pct": float(100 * abs(self.scale - 1)),
            "up_deg": self.up_deg,
            "offset_max_ms": float(1e3 * np.max(np.abs(self.offset_s))),
        }


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def compare_rigs(est: Rig, ref: Rig) -> RigComparison:
    """``est``'s errors against ``ref`` over the cameras both have (ValueError if fewer than
    three: a similarity of the centres needs three)."""
    names = [n for n in ref.names if n in est]
    if len(names) < 3:
        raise ValueError(f"rig comparison: {len(names)} common cameras, need 3")
    pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1 :]]
    rot = np.array([_angle_deg((est[a].R @ est[b].R.T) @ (ref[a].R @ ref[b].R.T).T) for a, b in pairs])
    A = np.stack([est[n].center for n in names])
    B = np.stack([ref[n].center for n in names])
    aligned, s, _, _ = procrustes_align(A[None], B[None])
    up = np.median([np.degrees(np.arccos(np.clip(est[n].R[:, 2] @ ref[n].R[:, 2], -1, 1))) for n in names])
    off = np.array([est[n].time_offset - ref[n].time_offset for n in names])
    return RigComparison(
        names=names,
        pairs=pairs,
        rotation_deg=rot,
        centre_m=np.linalg.norm(aligned[0] - B, axis=1),
        scale=float(1 / s[0]),
        up_deg=float(up),
        offset_s=off - np.median(off),
        radius_m=float(np.max(np.linalg.norm(B - B.mean(0), axis=1))),
    )


def format_comparison(c: RigComparison, what: str) -> str:
    """A few lines for a terminal."""
    s = c.summary()
    worst = c.pairs[int(np.argmax(c.rotation_deg))]
    lines = [
        f"against reference {what} ({len(c.names)} cameras):",
        f"  relative rotation deg: median {s['rot_median_deg']:.2f}, max "
        f"{s['rot_max_deg']:.2f} ({worst[0]}-{worst[1]})",
        f"  centres after a similarity alignment: median {100 * s['centre_median_m']:.1f} cm, "
        f"max {100 * s['centre_max_m']:.1f} cm ({s['centre_max_pct_radius']:.1f} % of the "
        f"rig radius {c.radius_m:.2f} m)",
        f"  scale: calibrated / reference {c.scale:.3f} ({s['scale_error_pct']:.1f} % off)",
        f"  up axis deg: {s['up_deg']:.2f}; time offsets: max {s['offset_max_ms']:.1f} ms apart",
    ]
    lines += [f"    {n}: centre {100 * e:.1f} cm" for n, e in zip(c.names, c.centre_m)]
    return "\n".join(lines)


def rig_similarity(est: Rig, ref: Rig) -> Similarity:
    """X_ref = s Q X_est + d moving ``est``'s world frame onto ``ref``'s: Q the rotation mean
    of the cameras' R_ref^T R_est (their orientations agree best), then s and d by least
    squares on the camera centres."""
    names = [n for n in ref.names if n in est]
    if len(names) < 2:
        raise ValueError(f"rig alignment: {len(names)} common cameras, need 2")
    M = sum(ref[n].R.T @ est[n].R for n in names)
    U, _, Vt = np.linalg.svd(M)
    Q = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    A = np.stack([est[n].center for n in names]) @ Q.T
    B = np.stack([ref[n].center for n in names])
    Ac, Bc = A - A.mean(0), B - B.mean(0)
    s = float(np.sum(Ac * Bc) / np.sum(Ac * Ac))
    return Similarity(s, Q, B.mean(0) - s * A.mean(0))


def aligned_rig(est: Rig, ref: Rig) -> Rig:
    """``est`` moved into ``ref``'s world frame by :func:`rig_similarity` (same intrinsics)."""
    sim = rig_similarity(est, ref)
    cams = []
    for cam in est:
        R, t = sim.camera(cam.R, cam.t)
        cams.append(replace(cam, R=R, t=t))
    return Rig(cams)
