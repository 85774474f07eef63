"""Geometry of a calibrated rig (world metres, rectified pinhole px).

- ``camera``: :class:`Camera` (intrinsics K, world->camera R, t, distortion) and :class:`Rig`
  (ordered named cameras; rig YAML, MAEM camera JSON, Qualisys and Pose2Sim files);
- ``rig_formats``: readers of other systems' calibration files (Qualisys ``.qca.txt``,
  Pose2Sim ``Calib.toml``);
- ``multiview``: batched weighted DLT and reprojection errors;
- ``procrustes``: similarity (Umeyama) alignment and PA-MPJPE;
- ``frames``: the rig as world -> camera transforms (what /tf_static carries).

Exports: Camera, Rig, fundamental_matrix, dlt, reprojection_error, reprojection_errors,
procrustes_align, pa_mpjpe, FrameTransform, rig_transforms.
"""

from maem_ros.core.geometry.camera import Camera, Rig, fundamental_matrix
from maem_ros.core.geometry.frames import FrameTransform, rig_transforms
from maem_ros.core.geometry.multiview import dlt, reprojection_error, reprojection_errors
from maem_ros.core.geometry.procrustes import pa_mpjpe, procrustes_align

__all__ = [
    "Camera",
    "Rig",
    "fundamental_matrix",
    "FrameTransform",
    "rig_transforms",
    "dlt",
    "reprojection_error",
    "reprojection_errors",
    "pa_mpjpe",
    "procrustes_align",
]
