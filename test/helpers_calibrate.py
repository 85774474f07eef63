"""Shared helpers of the calibration tests: constructed rigs looking at a court."""
from __future__ import annotations

import numpy as np

from maem_ros.core.geometry.camera import Camera, Rig
from maem_ros.sim.rigs import look_at


def ring_rig(n: int, radius: float = 12.0, height: float = 4.0, f: float = 1000.0,
             size: tuple[int, int] = (1280, 720), seed: int = 0, aim_jitter: float = 2.0) -> Rig:
    """n pinhole cameras on a ring around the origin (z up), looking at the court centre
    with a little random jitter of position and aim."""
    rng = np.random.default_rng(seed)
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n + rng.uniform(-0.2, 0.2)
        eye = np.array([radius * np.cos(a), radius * np.sin(a), height + rng.uniform(-1, 1)])
        target = np.array([rng.uniform(-aim_jitter, aim_jitter), rng.uniform(-aim_jitter, aim_jitter), 1.0])
        R, t = look_at(eye, target, roll=rng.uniform(-0.05, 0.05))
        w, h = size
        K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
        cams.append(Camera(name=f"cam{i}", K=K, R=R, t=t, width=w, height=h))
    return Rig(cams)


def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (deg) of Ra Rb^T."""
    c = (np.trace(Ra @ Rb.T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))
