"""Evaluation against ground truth (inputs in metres, errors reported in millimetres).

- ``poses``: the paper's metrics in the VoxelPose/Panoptic form (MPJPE, PA-MPJPE, Recall@500mm,
  AP@75/100/125/150);
- ``identity``: IDF1 and ID switches of tracked poses.

Exports: mpjpe, pa_mpjpe, evaluate_sequence, identity_metrics.
"""

from maem_ros.core.metrics.identity import identity_metrics
from maem_ros.core.metrics.poses import evaluate_sequence, mpjpe, pa_mpjpe

__all__ = ["evaluate_sequence", "identity_metrics", "mpjpe", "pa_mpjpe"]
