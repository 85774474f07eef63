"""Coordinate frames of a rig as transforms (what /tf_static carries): world -> each camera.

A camera's frame is its optical frame (OpenCV: x right, y down, z forward), named like the
camera (the frame_id of its images, camera_info and detections). The transform world -> camera
is the camera's pose in world: translation = camera centre (m, world), rotation = R^T (camera
axes in world), as a unit quaternion (x, y, z, w).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from maem_ros.core.geometry.camera import Rig


@dataclass(frozen=True)
class FrameTransform:
    """Pose of frame ``child`` in frame ``parent``: p_parent = rot(q) p_child + translation."""

    parent: str
    child: str
    translation: np.ndarray  # (3,) m
    quaternion: np.ndarray  # (4,) x y z w, unit

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N,3) points in ``child`` -> (N,3) in ``parent``."""
        return Rotation.from_quat(self.quaternion).apply(points) + self.translation


def rig_transforms(rig: Rig, world_frame: str = "world") -> list[FrameTransform]:
    """world -> camera for every camera of the rig, in rig order."""
    return [
        FrameTransform(
            world_frame,
            cam.name,
            np.asarray(cam.center, dtype=np.float64),
            Rotation.from_matrix(cam.R.T).as_quat(),
        )
        for cam in rig
    ]
