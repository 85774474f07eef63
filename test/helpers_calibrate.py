"""Shared helpers of the calibration tests: rig errors after alignment, simulated frames seen by
a rig file (the rigs themselves: helpers_scene.ring_rig with CALIBRATION_RING and a jitter)."""
from __future__ import annotations

import numpy as np


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (deg) of Ra Rb^T."""
    c = (np.trace(Ra @ Rb.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def sim_frames(rig_path, frames: int, players: int, difficulty: str = "none", bystanders: int = 0,
               seed: int = 0, time_offsets: dict | None = None):
    """({camera: [FrameDetections]}, the scene) of a simulated scene seen by the rig file."""
    from maem_ros.sim.scene import Scene, SceneConfig
    scene = Scene(SceneConfig(rig=str(rig_path), frames=frames, difficulty=difficulty,
                              players=players, bystanders=bystanders, num_vertices=19, seed=seed,
                              time_offsets=time_offsets or {}))
    return {c.name: [scene.detections(c.name, f) for f in range(frames)] for c in scene.rig}, scene


def aligned_errors(rig_est, rig_true) -> dict:
    """Relative rotation errors (deg, every pair), centre errors after a similarity alignment
    (m), the alignment's scale, for rigs with the same camera names."""
    from maem_ros.core.geometry.procrustes import procrustes_align
    names = rig_est.names
    rot = [rotation_angle_deg(rig_est[a].R @ rig_est[b].R.T, rig_true[a].R @ rig_true[b].R.T)
           for i, a in enumerate(names) for b in names[i + 1:]]
    A = np.stack([rig_est[n].center for n in names])
    B = np.stack([rig_true[n].center for n in names])
    if len(names) < 3:  # two cameras: compare in camera 0's frame (a similarity needs 3 points)
        A = (A - A[0]) @ rig_est[0].R.T
        B = (B - B[0]) @ rig_true[0].R.T
        s = np.array([np.linalg.norm(B[1]) / np.linalg.norm(A[1])])
        aligned = (s[0] * A)[None]
        return {"rot_median": float(np.median(rot)), "rot_max": float(np.max(rot)),
                "centre_max": float(np.max(np.linalg.norm(aligned[0] - B, axis=1))),
                "scale": float(s[0]), "radius": float(np.linalg.norm(B[1]) / 2)}
    aligned, s, _, _ = procrustes_align(A[None], B[None])
    radius = float(np.max(np.linalg.norm(B - B.mean(0), axis=1)))
    return {"rot_median": float(np.median(rot)), "rot_max": float(np.max(rot)),
            "centre_max": float(np.max(np.linalg.norm(aligned[0] - B, axis=1))),
            "scale": float(s[0]), "radius": radius}
